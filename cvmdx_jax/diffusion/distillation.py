"""Distillation of the guided denoiser into few-step students, beyond the paper.

Two stages, each a plain regression of the student's v onto a teacher target at the
same (x_t, t):

1. Guidance distillation (Meng et al. 2023, "On distillation of guided diffusion
   models"): the student v_s(x_t, t, q, [c, w]) takes the guidance weight w as one more
   FiLM feature and regresses the guided v of the teacher's conditional / unconditional
   pair at w = w(t, delta) (`guidance.guided_v_fn`): one evaluation replaces the pair.
2. Progressive distillation (Salimans & Ho 2022, Algorithm 2): a student for S steps
   regresses the x0 with which one deterministic DDIM step t_i -> t_{i+1} lands where two
   teacher steps t_i -> t_mid -> t_{i+1} land (teacher: the previous student at 2S steps):

     x_n = two teacher DDIM steps from x_t,   r = sigma_n / sigma_t,
     x0~ = (x_n - r x_t) / (alpha_n - r alpha_t),   (alpha_n = 1, sigma_n = 0 at the end)

   expressed as its v (`param.v_from_x0_eps`) so the loss is the training v-loss.
   With the guided pair of the teacher denoiser as the teacher (`train.distill`'s
   "guided_progressive" stage) the two stages are one.

The students sample with `distilled_sample`: deterministic DDIM over
`distilled_timesteps` (S evaluations, the last update to abar = 1). The grids are nested
(`distilled_timesteps(T, 2S)[::2] == distilled_timesteps(T, S)`), as progressive
distillation needs.
"""

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.diffusion import param
from cvmdx_jax.diffusion.samplers import initial_noise, predict_x0_eps
from cvmdx_jax.diffusion.schedule import Schedule


def student_cond(ego, w):
  """The FiLM input of a guidance student: [ego features (B, F) if any, w (B,)] -> (B, F + 1)."""
  w = jnp.asarray(w, jnp.float32)[:, None]
  return w if ego is None else jnp.concatenate([ego, w], axis=-1)


def distilled_timesteps(num_steps: int, steps: int) -> np.ndarray:
  """The S evaluation timesteps t_i = round((T - 1)(S - i) / S), halves rounded up,
  i = 0..S-1, in exact integer arithmetic (so the grid of 2S holds the grid of S at its
  even positions).

  Returns:
    (S,) int32, strictly decreasing from T - 1.
  """
  if not 1 <= steps < num_steps:
    raise ValueError(f"distilled steps must be in [1, {num_steps - 1}], got {steps}")
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


def distilled_sample(v_fn, key, shape, schedule: Schedule, steps: int,
                     clip_x0: float | None = None, x_T: jax.Array | None = None):
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


def progressive_grid(schedule: Schedule, steps: int, index: jax.Array):
  """Per-example (t, t_mid, abar_t, abar_mid, abar_next) of student step `index` (B,) of
  an S-step student, with the teacher's 2S-step grid in between."""
  teacher_t, teacher_abar, teacher_next = step_abars(schedule, 2 * steps)
  first, second = 2 * index, 2 * index + 1
  return (teacher_t[first], teacher_t[second], teacher_abar[first], teacher_abar[second],
          teacher_next[second])


def progressive_target(teacher_v_fn, x_t, t, t_mid, abar_t, abar_mid, abar_next,
                       clip_x0: float | None = None):
  """The v-target of a progressive student at (x_t, t) (module docstring).

  Args:
    teacher_v_fn: (x, t (B,)) -> v of the teacher (one evaluation per step).
    x_t: (B, ...) noisy inputs at t.
    t, t_mid: (B,) int timesteps of the two teacher steps.
    abar_t, abar_mid, abar_next: (B,) abar at t, t_mid and the step's target (1 = clean).
    clip_x0: the sampler's clip of predicted x0.

  Returns:
    (B, ...) v at (x_t, abar_t) of the x0 that one DDIM step must use to reach the teacher's
    two-step result.
  """
  x0, eps = predict_x0_eps(teacher_v_fn, x_t, t, abar_t, clip_x0)
  x_mid = ddim_update(x0, eps, abar_mid)
  x0, eps = predict_x0_eps(teacher_v_fn, x_mid, t_mid, abar_mid, clip_x0)
  x_next = ddim_update(x0, eps, abar_next)
  expand = lambda a: jnp.reshape(a, a.shape + (1,) * (x_t.ndim - a.ndim))
  a_t, a_next = expand(abar_t), expand(abar_next)
  ratio = jnp.sqrt((1.0 - a_next) / (1.0 - a_t))
  x0_target = (x_next - ratio * x_t) / (jnp.sqrt(a_next) - ratio * jnp.sqrt(a_t))
  return param.v_from_x0_eps(x0_target, param.eps_from_x0(x_t, x0_target, abar_t), abar_t)
