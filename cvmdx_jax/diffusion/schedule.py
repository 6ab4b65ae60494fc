"""Noise schedules: the cosine schedule (T = 1000) and DDIM timestep subsets."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.errors import UserError


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Schedule:
  """Discrete forward process; index t in [0, T) means
  x_t = sqrt(alphas_cumprod[t]) x0 + sqrt(1 - alphas_cumprod[t]) eps.

  Attributes:
    betas: (T,) per-step noise variances beta_t.
    alphas_cumprod: (T,) abar_t = prod_{s<=t} (1 - beta_s).
  """

  betas: jax.Array
  alphas_cumprod: jax.Array

  @property
  def num_steps(self) -> int:
    return self.betas.shape[0]


def cosine_schedule(
    num_steps: int = 1000, offset: float = 0.008, max_beta: float = 0.999
) -> Schedule:
  """Cosine schedule of Nichol & Dhariwal (2021):
  abar(u) = cos^2((u + s) / (1 + s) * pi / 2),
  beta_t = min(1 - abar((t+1)/T) / abar(t/T), max_beta).
  """
  u = np.arange(num_steps + 1, dtype=np.float64) / num_steps
  f = np.cos((u + offset) / (1.0 + offset) * math.pi / 2.0) ** 2
  betas = np.minimum(1.0 - f[1:] / f[:-1], max_beta)
  abar = np.cumprod(1.0 - betas)
  return Schedule(
      betas=jnp.asarray(betas, jnp.float32), alphas_cumprod=jnp.asarray(abar, jnp.float32)
  )


def ddim_timesteps(num_steps: int, steps: int) -> np.ndarray:
  """S timesteps linearly spaced over [0, T-1], descending (the order of sampling).

  Returns:
    (S,) int32, first element T-1, last element 0.
  """
  if not 1 <= steps <= num_steps:
    raise UserError(f"DDIM steps must be in [1, {num_steps}], got {steps}")
  grid = np.round(np.linspace(0, num_steps - 1, steps)).astype(np.int32)
  return grid[::-1].copy()


def official_ddim_timesteps(num_steps: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
  """The official cVMDx DDIM grid: floor(linspace(0, T-1, steps))[1:], descending,
  each step going to the next grid point and the last to t = 0
  (T = 1000, steps = 10: 999, 888, ..., 111 -> 888, ..., 111, 0; 9 updates).

  Returns:
    (t, t_prev), each (steps - 1,) int32.
  """
  if not 2 <= steps <= num_steps:
    raise UserError(f"official DDIM steps must be in [2, {num_steps}], got {steps}")
  grid = np.floor(np.linspace(0, num_steps - 1, steps)).astype(np.int32)[1:][::-1]
  return grid.copy(), np.append(grid[1:], 0).astype(np.int32)
