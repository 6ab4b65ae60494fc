"""`official_ddim_sample` (sampling.mode="official") against a numpy float32 loop of the
official guided DDIM update written from its equations, with an analytic denoiser whose
outputs are exact in float32 (so both sides see the same v)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import diffusion
from cvmdx_jax.config.sampling import GuidanceConfig, SamplingConfig
from cvmdx_jax.inference import sampling as sampling_lib
from cvmdx_jax.models import unet1d
from tests.models import tiny_nets

NULL = 5
F32 = np.float32


def analytic_v(x, t, q):
  """0.5 x + c(q, t) with c a multiple of 2^-12: every operation exact or rounded once."""
  c = jnp.where(q == NULL, -0.25, 0.125)[:, None, None] + t[:, None, None] * 2.0**-12
  return 0.5 * x + c


def numpy_official(x_T, abar, steps, w_start, w_end, clip, eta=0.0, noises=None):
  """The official ddim_sample_loop in float32, one rounding per operation, for
  `analytic_v` with a non-null token."""
  grid = [int(np.floor(v)) for v in np.linspace(0, len(abar) - 1, steps)][1:][::-1]
  prev = grid[1:] + [0]
  n = len(grid)
  w = [
      F32(w_start + (w_end - w_start) * (1 - np.cos(np.pi * i / (n - 1))) / 2)
      if n > 1
      else F32(w_start)
      for i in range(n)
  ]
  x = x_T.astype(F32)
  c_cond = F32(0.125)
  for i, (t, tp) in enumerate(zip(grid, prev)):
    a_t, a_p = F32(abar[t]), F32(abar[tp])
    alpha, sigma = np.sqrt(a_t), np.sqrt(F32(1) - a_t)
    v_c = F32(0.5) * x + (c_cond + F32(t * 2.0**-12))
    v_u = F32(0.5) * x + (F32(-0.25) + F32(t * 2.0**-12))
    eps_c = sigma * x + alpha * v_c
    eps_u = sigma * x + alpha * v_u
    eps = eps_u + w[i] * (eps_c - eps_u)
    x0 = (x - sigma * eps) / alpha
    if clip is not None:
      x0 = np.clip(x0, -clip, clip)
    s = F32(eta) * np.sqrt((F32(1) - a_p) / (F32(1) - a_t)) * np.sqrt(F32(1) - a_t / a_p)
    x = np.sqrt(a_p) * x0 + np.sqrt(np.maximum(F32(1) - a_p - s * s, F32(0))) * eps
    if noises is not None and tp > 0:
      x = x + s * noises[i]
  return x


@pytest.fixture(scope="module")
def schedule():
  return diffusion.cosine_schedule(1000)


def test_official_grid_and_weights():
  t, t_prev = diffusion.official_ddim_timesteps(1000, 10)
  assert t.tolist() == [999, 888, 777, 666, 555, 444, 333, 222, 111]
  assert t_prev.tolist() == [888, 777, 666, 555, 444, 333, 222, 111, 0]
  # floor(linspace(0, 999, 7)) = 0, 166, 333, 499, 666, 832, 999
  assert diffusion.official_ddim_timesteps(1000, 7)[0].tolist() == [999, 832, 666, 499, 333, 166]
  np.testing.assert_allclose(
      diffusion.official_step_weights(9),
      [0.1, 0.134, 0.232, 0.378, 0.55, 0.722, 0.868, 0.966, 1.0],
      atol=1e-3,
  )
  with pytest.raises(ValueError, match="official DDIM steps"):
    diffusion.official_ddim_timesteps(1000, 1)


@pytest.mark.parametrize(
    "steps,clip,w", [(10, 1.0, (0.1, 1.0)), (10, None, (0.1, 1.0)), (7, 1.0, (0.3, 0.6))]
)
def test_official_loop_equals_numpy_reference(schedule, steps, clip, w):
  shape = (6, 125, 2)
  x_T = jax.random.normal(jax.random.key(3), shape)
  q = jnp.full((6,), 2)
  fn = diffusion.cond_uncond_v_fn(analytic_v, q, NULL)
  got = jax.jit(
      lambda x: diffusion.official_ddim_sample(
          fn,
          jax.random.key(0),
          shape,
          schedule,
          steps=steps,
          clip_x0=clip,
          w_start=w[0],
          w_end=w[1],
          x_T=x,
      )
  )(x_T)
  want = numpy_official(np.asarray(x_T), np.asarray(schedule.alphas_cumprod), steps, *w, clip)
  np.testing.assert_allclose(got, want, atol=1e-5)
  # the paper-mode loop with the official guidance form and direction is another sampler
  cfg = GuidanceConfig(form="official", direction="official")
  v_fn = diffusion.guided_v_fn(analytic_v, q, NULL, jnp.zeros(6), schedule, cfg)
  paper = diffusion.ddim_sample(
      v_fn, jax.random.key(0), shape, schedule, steps=steps, clip_x0=clip, x_T=x_T
  )
  assert np.abs(np.asarray(paper) - want).max() > 1e-3


def test_official_loop_with_noise(schedule):
  shape, steps, key = (4, 125, 2), 10, jax.random.key(5)
  x_T = jax.random.normal(jax.random.key(6), shape)
  fn = diffusion.cond_uncond_v_fn(analytic_v, jnp.full((4,), 1), NULL)
  got = diffusion.official_ddim_sample(fn, key, shape, schedule, steps=steps, eta=0.7, x_T=x_T)
  noises = [
      np.asarray(jax.random.normal(jax.random.fold_in(key, i), shape)) for i in range(steps - 1)
  ]
  want = numpy_official(
      np.asarray(x_T),
      np.asarray(schedule.alphas_cumprod),
      steps,
      0.1,
      1.0,
      1.0,
      eta=0.7,
      noises=noises,
  )
  np.testing.assert_allclose(got, want, atol=1e-5)
  # without x_T the initial noise comes from fold_in(key, steps)
  own = diffusion.official_ddim_sample(fn, key, shape, schedule, steps=steps, eta=0.7)
  np.testing.assert_array_equal(
      own,
      diffusion.official_ddim_sample(
          fn,
          key,
          shape,
          schedule,
          steps=steps,
          eta=0.7,
          x_T=jax.random.normal(jax.random.fold_in(key, steps), shape),
      ),
  )
  with pytest.raises(ValueError, match="x_T has shape"):
    diffusion.official_ddim_sample(fn, key, shape, schedule, x_T=jnp.zeros((4, 125, 1)))


def test_samplers_take_an_explicit_x_T(schedule):
  v_fn = lambda x, t: 0.5 * x
  key, shape = jax.random.key(2), (3, 125, 2)
  for sample, index in (
      (lambda **k: diffusion.ddim_sample(v_fn, key, shape, schedule, steps=5, **k), 5),
      (lambda **k: diffusion.ddpm_sample(v_fn, key, shape, schedule, **k), 1000),
  ):
    own_noise = jax.random.normal(jax.random.fold_in(key, index), shape)
    default, same, other = jax.jit(lambda x: (sample(), sample(x_T=x), sample(x_T=2 * x)))(
        own_noise
    )
    np.testing.assert_array_equal(default, same)
    assert not np.allclose(same, other)


@pytest.mark.slow
def test_inference_official_mode_runs_the_official_loop(schedule):
  cfg = tiny_nets.unet_config(4, attention_levels=())
  g, p = unet1d.init_unet(cfg, jax.random.key(0))
  p = jax.tree.map(lambda a: a + 0.02 * jax.random.normal(jax.random.key(1), a.shape), p)
  sampling = SamplingConfig(
      num_samples=3, mode="official", steps=5, guidance=GuidanceConfig(w_min=0.2, w_max_base=0.8)
  )
  key = jax.random.key(4)
  model = lambda x, t, c: unet1d.apply_unet(g, p, x, t, c)
  fn = diffusion.cond_uncond_v_fn(model, jnp.full((3,), 1), cfg.null_token)

  @jax.jit
  def both(p):
    got = sampling_lib.sample_controls(
        g, p, 1, 80.0, key, schedule=schedule, null_token=cfg.null_token, config=sampling
    )
    return got, diffusion.official_ddim_sample(
        fn, key, (3, 125, 2), schedule, steps=5, w_start=0.2, w_end=0.8
    )

  got, want = both(p)
  np.testing.assert_allclose(got, want, atol=1e-5)
  with pytest.raises(ValueError, match="mode"):
    SamplingConfig(mode="official", sampler="ddpm")
  with pytest.raises(ValueError, match="mode"):
    dataclasses.replace(sampling, mode="torch")
