"""Distillation maths: the nested grids, the distilled sampler on exact Gaussian data, and
the progressive target against its definition (one student step = two teacher steps)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import diffusion
from cvmdx_jax.diffusion import distillation, solvers
from tests.diffusion.gaussian_data import MU, STD, gaussian_v


@pytest.fixture(scope="module")
def schedule():
  return diffusion.cosine_schedule(1000)


def test_grids_are_nested_and_hand_worked():
  # (T - 1)(S - i) / S rounded, halves up: 999 * 3 / 4 = 749.25, 999 / 4 = 249.75
  np.testing.assert_array_equal(distillation.distilled_timesteps(1000, 4), [999, 749, 500, 250])
  np.testing.assert_array_equal(distillation.distilled_timesteps(1000, 2), [999, 500])
  np.testing.assert_array_equal(distillation.distilled_timesteps(1000, 1), [999])
  # 999 * (10 - i) / 10: 899.1, 799.2, ..., 99.9 (rounded)
  np.testing.assert_array_equal(
      distillation.distilled_timesteps(1000, 10), [999, 899, 799, 699, 599, 500, 400, 300, 200, 100]
  )
  for k in (2, 3, 5):
    for steps in (1, 2, 3, 4, 5, 8, 16, 64, 199):
      fine, coarse = (distillation.distilled_timesteps(1000, s) for s in (k * steps, steps))
      np.testing.assert_array_equal(fine[::k], coarse)
      assert fine[0] == 999 and np.all(np.diff(fine) < 0) and fine[-1] > 0
  for bad in (0, 1000):
    with pytest.raises(ValueError, match="steps"):
      distillation.distilled_timesteps(1000, bad)


def test_distilled_sample_of_the_exact_denoiser_converges_to_the_ode_map(schedule):
  """With the exact v of Gaussian data, DDIM to abar = 1 approaches the probability-flow
  ODE's map x_T -> MU + STD (x_T - m_T) / s_T as the steps grow."""
  v_fn = lambda x, t: gaussian_v(x, t, schedule.alphas_cumprod)
  x_T = jax.random.normal(jax.random.key(0), (128, 4, 2))
  abar_T = float(schedule.alphas_cumprod[999])
  exact = MU + STD * (np.asarray(x_T) - np.sqrt(abar_T) * MU) / np.sqrt(
      abar_T * STD**2 + 1.0 - abar_T
  )
  sample = lambda s: distillation.distilled_sample(v_fn, None, x_T.shape, schedule, s, x_T=x_T)
  errors = [float(np.abs(sample(s) - exact).max()) for s in (4, 16, 256)]
  assert errors[0] > errors[1] > errors[2] and errors[2] < 0.02  # first order: ~1 / S
  for s in (1, 2):  # DPM-Solver++(2M) is first order on its first and last step: DDIM
    np.testing.assert_allclose(
        sample(s),
        solvers.dpmpp_2m_sample(v_fn, None, x_T.shape, schedule, steps=s, x_T=x_T),
        atol=1e-6,
    )


def _teacher(schedule):
  """A teacher with x-dependence the Gaussian's exact v does not have (nonlinear in x)."""
  return lambda x, t: (
      gaussian_v(x, t, schedule.alphas_cumprod)
      + 0.1 * jnp.sin(3.0 * x) * (t[:, None, None] / 1000.0)
  )


@pytest.mark.parametrize("substeps", [2, 5])
def test_one_step_with_the_target_lands_where_k_teacher_steps_land(schedule, substeps):
  teacher = _teacher(schedule)
  steps = 4
  index = jnp.array([0, 1, 2, 3, 3, 0])
  ts, a_ts, a_next = distillation.progressive_grid(schedule, steps, index, substeps)
  fine = distillation.distilled_timesteps(1000, substeps * steps)
  np.testing.assert_array_equal(ts[:, 0], distillation.distilled_timesteps(1000, 4)[index])
  for j in range(substeps):
    np.testing.assert_array_equal(ts[:, j], fine[substeps * index + j])
  np.testing.assert_array_equal(a_next[index == 3], 1.0)
  np.testing.assert_array_equal(
      a_next[index < 3], schedule.alphas_cumprod[fine[substeps * (index[index < 3] + 1)]]
  )
  x_t = jax.random.normal(jax.random.key(1), (6, 5, 2))
  v = distillation.progressive_target(teacher, x_t, ts, a_ts, a_next)
  student = diffusion.x0_from_v(x_t, v, a_ts[:, 0]), diffusion.eps_from_v(x_t, v, a_ts[:, 0])
  one = distillation.ddim_update(*student, a_next)
  # k teacher steps, written out with the parameterisation's own formulas
  x = x_t
  ends = [a_ts[:, j] for j in range(1, substeps)] + [a_next]
  for j, a_to in enumerate(ends):
    a, v_teacher = a_ts[:, j], teacher(x, ts[:, j])
    x0, eps = diffusion.x0_from_v(x, v_teacher, a), diffusion.eps_from_v(x, v_teacher, a)
    x = jnp.sqrt(a_to)[:, None, None] * x0 + jnp.sqrt(1.0 - a_to)[:, None, None] * eps
  np.testing.assert_allclose(one, x, atol=2e-5)


@pytest.mark.parametrize("substeps", [2, 5])
def test_a_student_of_exact_targets_samples_as_the_teacher_at_k_times_the_steps(schedule, substeps):
  teacher = _teacher(schedule)
  steps = 2 if substeps == 5 else 4
  grid = jnp.asarray(distillation.distilled_timesteps(1000, steps))

  def student(x, t):
    index = jnp.argmax(grid[None, :] == t[:, None], axis=1)
    return distillation.progressive_target(
        teacher, x, *distillation.progressive_grid(schedule, steps, index, substeps)
    )

  x_T = jax.random.normal(jax.random.key(2), (64, 5, 2))
  fast = distillation.distilled_sample(student, None, x_T.shape, schedule, steps, x_T=x_T)
  slow = distillation.distilled_sample(
      teacher, None, x_T.shape, schedule, substeps * steps, x_T=x_T
  )
  np.testing.assert_allclose(fast, slow, atol=1e-4)


def test_student_cond_appends_w_as_the_last_feature():
  w = jnp.array([0.25, 0.5])
  np.testing.assert_array_equal(distillation.student_cond(None, w), [[0.25], [0.5]])
  ego = jnp.arange(6.0).reshape(2, 3)
  np.testing.assert_array_equal(
      distillation.student_cond(ego, w), [[0, 1, 2, 0.25], [3, 4, 5, 0.5]]
  )
