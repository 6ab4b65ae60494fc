"""Distillation of the guided denoiser into few-step students, beyond the paper.

Two stages, each a plain regression of the student's v onto a teacher target at the
same (x_t, t):

1. Guidance distillation (Meng et al. 2023, "On distillation of guided diffusion
   models"): the student v_s(x_t, t, q, [c, w]) takes the guidance weight w as one more
   FiLM feature and regresses the guided v of the teacher's conditional / unconditional
   pair at w = w(t, delta) (`guidance.guided_v_fn`): one evaluation replaces the pair.
2. Progressive distillation (Salimans & Ho 2022, Algorithm 2): a student for S steps
   regresses the x0 with which one deterministic DDIM step t_i -> t_{i+1} lands where two
   teacher steps t_i -> t_mid -> t_{i+1} land (teacher: the previous student at 2S steps),
   or, generally, where k teacher steps of the grid of k S land (`substeps` = k; k = 5
   with S = 2 regresses the teacher's 10-step DDIM):

     x_n = k teacher DDIM steps from x_t,   r = sigma_n / sigma_t,
     x0~ = (x_n - r x_t) / (alpha_n - r alpha_t),   (alpha_n = 1, sigma_n = 0 at the end)

   expressed as its v (`param.v_from_x0_eps`) so the loss is the training v-loss.
   With the guided pair of the teacher denoiser as the teacher (`train.distill`'s
   "guided_progressive" stage) the two stages are one.

The students sample with `distilled_sample`: deterministic DDIM over
`distilled_timesteps` (S evaluations, the last update to abar = 1). The grids are nested
(`distilled_timesteps(T, k S)[::k] == distilled_timesteps(T, S)`), as progressive
distillation needs.
"""

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.diffusion import param
from cvmdx_jax.diffusion.samplers import initial_noise, predict_x0_eps
from cvmdx_jax.diffusion.schedule import Schedule
from cvmdx_jax.errors import UserError


def student_cond(ego, w):
  """The FiLM input of a guidance student: [ego features (B, F) if any, w (B,)] -> (B, F + 1)."""
  w = jnp.asarray(w, jnp.float32)[:, None]
  return w if ego is None else jnp.concatenate([ego, w], axis=-1)


def distilled_timesteps(num_steps: int, steps: int) -> np.ndarray:
  """The S evaluation timesteps t_i = round((T - 1)(S - i) / S), halves rounded up,
  i = 0..S-1, in exact integer arithmetic (so the grid of k S holds the grid of S at every
  k-th position).

  Returns:
    (S,) int32, strictly decreasing from T - 1.
  """
  if not 1 <= steps < num_steps:
    raise UserError(f"distilled steps must be in [1, {num_steps - 1}], got {steps}")
  i = np.arange(steps, dtype=np.int64)
  return ((2 * (num_steps - 1) * (steps - i) + steps) // (2 * steps)).astype(np.int32)


def step_abars(schedule: Schedule, steps: int) -> tuple[jax.Array, jax.Array, jax.Array]:
  """(t (S,), abar_t (S,), abar_next (S,)) of the S-step grid; abar_next of the last
  step is 1 (the clean sample)."""
  ts = jnp.asarray(distilled_timesteps(schedule.num_steps, steps))
  abar_t = schedule.alphas_cumprod[ts]
  return ts, abar_t, jnp.concatenate([abar_t[1:], jnp.ones((1,), abar_t.dtype)])


def ddim_update(x0, eps, abar_next):
  """One deterministic DDIM update to abar_next (broadcast from the left):
  sqrt(abar_next) x0 + sqrt(1 - abar_next) eps."""
  return param.q_sample(x0, eps, abar_next)


def distilled_sample(
    v_fn,
    key,
    shape,
    schedule: Schedule,
    steps: int,
    clip_x0: float | None = None,
    x_T: jax.Array | None = None,
):
  """Deterministic DDIM over `distilled_timesteps` (S evaluations of `v_fn`).

  Args:
    v_fn: (x_t, t (B,)) -> v, one evaluation per step (a guidance student).
    key: PRNG key of x_T = N(0, I) (`fold_in(key, steps)`, as DDIM); unused if x_T given.
    shape: sample shape, leading dim = batch.
    schedule: the training `Schedule`.
    steps: S.
    clip_x0: clip each predicted x0 to [-clip_x0, clip_x0] (None: no clip).
    x_T: optional initial noise of `shape`.

  Returns:
    x0 samples of `shape`.
  """
  ts, abar_t, abar_next = step_abars(schedule, steps)
  x_T = initial_noise(key, steps, shape, x_T)

  def body(x, inputs):
    t, a_t, a_next = inputs
    x0, eps = predict_x0_eps(v_fn, x, t, a_t, clip_x0)
    return ddim_update(x0, eps, a_next), None

  x0, _ = jax.lax.scan(body, x_T, (ts, abar_t, abar_next))
  return x0


def progressive_grid(schedule: Schedule, steps: int, index: jax.Array, substeps: int):
  """The teacher's steps inside student step `index` (B,) of an S-step student: the grid of
  `substeps` x S holds the student's grid at every `substeps`-th position.

  Returns:
    (ts (B, k), abars (B, k), abar_next (B,)): the k = `substeps` teacher timesteps from the
    student's t on, their abar, and the abar the student step ends at (1 = clean).
  """
  teacher_t, teacher_abar, teacher_next = step_abars(schedule, substeps * steps)
  positions = substeps * index[:, None] + jnp.arange(substeps)
  return teacher_t[positions], teacher_abar[positions], teacher_next[positions[:, -1]]


def progressive_target(teacher_v_fn, x_t, ts, abars, abar_next, clip_x0: float | None = None):
  """The v-target of a progressive student at (x_t, ts[:, 0]) (module docstring).

  Args:
    teacher_v_fn: (x, t (B,)) -> v of the teacher (one evaluation per step).
    x_t: (B, ...) noisy inputs at ts[:, 0].
    ts: (B, k) int timesteps of the teacher's k DDIM steps.
    abars: (B, k) abar at ts; abar_next: (B,) abar of the step's end (1 = clean).
    clip_x0: the sampler's clip of predicted x0.

  Returns:
    (B, ...) v at (x_t, abars[:, 0]) of the x0 that one DDIM step must use to reach the
    teacher's k-step result.
  """
  ends = jnp.concatenate([abars[:, 1:], abar_next[:, None]], axis=1)

  def teacher_step(x, step):  # one teacher DDIM step; a scan: one U-Net in the program
    t, a_t, a_end = step
    x0, eps = predict_x0_eps(teacher_v_fn, x, t, a_t, clip_x0)
    return ddim_update(x0, eps, a_end), None

  x, _ = jax.lax.scan(teacher_step, x_t, (ts.T, abars.T, ends.T))
  expand = lambda a: jnp.reshape(a, a.shape + (1,) * (x_t.ndim - a.ndim))
  abar_t = abars[:, 0]
  a_t, a_next = expand(abar_t), expand(abar_next)
  ratio = jnp.sqrt((1.0 - a_next) / (1.0 - a_t))
  x0_target = (x - ratio * x_t) / (jnp.sqrt(a_next) - ratio * jnp.sqrt(a_t))
  return param.v_from_x0_eps(x0_target, param.eps_from_x0(x_t, x0_target, abar_t), abar_t)
