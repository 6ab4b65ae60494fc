"""The jitted inference path: shapes, physics, determinism, batch independence."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import diffusion, ego_motion, vmm
from cvmdx_jax.config.denoiser import PAPER_SCALE, DenoiserConfig
from cvmdx_jax.config.sampling import GuidanceConfig, SamplingConfig
from cvmdx_jax.inference import sampling
from cvmdx_jax.models import unet1d
from tests.inference.denoisers import bundle
from tests.models import tiny_nets

CFG = tiny_nets.unet_config(4)
SAMPLING = SamplingConfig(num_samples=9, steps=4)
predict_batch = jax.jit(sampling.predict_batch, static_argnames=sampling.STATIC_ARGNAMES)


@pytest.fixture(scope="module")
def model():
  g, p = unet1d.init_unet(CFG, jax.random.key(0))
  p = jax.tree.map(lambda a: a + 0.02 * jax.random.normal(jax.random.key(1), a.shape), p)
  return g, p


def _predict(model, keys, b=3, config=SAMPLING, denoiser=DenoiserConfig()):
  g, p = model
  q = jnp.arange(b) % 4
  return predict_batch(
      bundle(g, p, CFG, denoiser),
      q,
      jnp.linspace(0.0, 60.0, b),
      jnp.full(b, 30.0),
      jnp.zeros(b),
      keys,
      schedule=diffusion.cosine_schedule(),
      config=config,
  )


def test_shapes_and_consistency(model):
  keys = jax.random.split(jax.random.key(0), 3)
  out = _predict(model, keys)
  assert out.controls.shape == out.trajectories.shape == (3, 9, 125, 2)
  assert out.mean.shape == (3, 125, 2)
  assert out.hypotheses.means.shape == (3, 3, 125, 2)
  np.testing.assert_allclose(out.hypotheses.probs.sum(-1), 1.0, atol=1e-6)
  np.testing.assert_allclose(out.mean, out.trajectories.mean(1), atol=1e-4)
  # trajectories are the VMM rollout of the controls, which stay in the normalised caps
  np.testing.assert_allclose(out.trajectories, vmm.rollout(out.controls, 30.0, 0.0), atol=1e-3)
  x0 = out.controls / jnp.asarray(PAPER_SCALE)
  assert float(jnp.abs(x0).max()) <= 1.0 + 1e-5


@pytest.mark.usefixtures("float32_arithmetic")  # batch sizes pick other TF32 kernels on a GPU
def test_deterministic_and_batch_independent(model):
  keys = jax.random.split(jax.random.key(7), 3)
  a, b = _predict(model, keys), _predict(model, keys)
  np.testing.assert_array_equal(a.trajectories, b.trajectories)
  other = _predict(model, jax.random.split(jax.random.key(8), 3))
  assert not np.allclose(a.trajectories, other.trajectories)
  g, p = model
  solo = predict_batch(
      bundle(g, p, CFG),
      jnp.array([1]),
      jnp.array([30.0]),
      jnp.array([30.0]),
      jnp.zeros(1),
      keys[1:2],
      schedule=diffusion.cosine_schedule(),
      config=SAMPLING,
  )
  np.testing.assert_allclose(solo.trajectories[0], a.trajectories[1], atol=1e-3)


def test_ddpm_path_and_bad_config(model):
  cfg = dataclasses.replace(
      SAMPLING,
      sampler="ddpm",
      num_samples=3,
      hypotheses=dataclasses.replace(SAMPLING.hypotheses, c_max=2),
  )
  out = _predict(model, jax.random.split(jax.random.key(0), 2), b=2, config=cfg)
  assert out.trajectories.shape == (2, 3, 125, 2)
  with pytest.raises(ValueError, match="sampler"):
    SamplingConfig(sampler="euler")


def test_control_scale_sets_the_physical_range(model):
  keys = jax.random.split(jax.random.key(0), 2)
  narrow = DenoiserConfig(control_scale=(2.0, 0.1))
  a = _predict(model, keys, b=2)
  b = _predict(model, keys, b=2, denoiser=narrow)
  # same normalised samples, other physical units
  np.testing.assert_allclose(b.controls[..., 0] * 2.0, a.controls[..., 0], rtol=1e-4, atol=1e-6)
  np.testing.assert_allclose(b.controls[..., 1] * 7.0, a.controls[..., 1], rtol=1e-4, atol=1e-6)
  assert float(jnp.abs(b.controls[..., 1]).max()) <= 0.1 + 1e-6


def _predict_ego(g, p, ego, keys, config, denoiser, unet=CFG):
  b = ego.shape[0]
  return sampling.predict_batch(
      bundle(g, p, unet, denoiser),
      jnp.arange(b) % 4,
      jnp.full(b, 10.0),
      jnp.full(b, 30.0),
      jnp.zeros(b),
      keys,
      ego,
      schedule=diffusion.cosine_schedule(),
      config=config,
  )


@pytest.mark.slow
def test_ego_film_reaches_the_unconditional_branch():
  cfg = dataclasses.replace(CFG, cond_dim=ego_motion.NUM_FEATURES)
  g, p = unet1d.init_unet(cfg, jax.random.key(2))
  p = jax.tree.map(lambda a: a + 0.02 * jax.random.normal(jax.random.key(3), a.shape), p)
  ego = jax.random.normal(jax.random.key(4), (2, ego_motion.NUM_FEATURES))
  keys = jax.random.split(jax.random.key(5), 2)
  # official form with w = 0 everywhere: the guided v is the unconditional branch alone
  uncond_only = dataclasses.replace(
      SAMPLING, guidance=GuidanceConfig(w_min=0.0, w_max_base=0.0, form="official")
  )
  film = DenoiserConfig(conditioning="ego_film")
  a = _predict_ego(g, p, ego, keys, uncond_only, film, cfg)
  b = _predict_ego(g, p, ego.at[:, 0].add(2.0), keys, uncond_only, film, cfg)
  assert not np.allclose(a.controls, b.controls)
  np.testing.assert_array_equal(
      a.controls, _predict_ego(g, p, ego, keys, uncond_only, film, cfg).controls
  )
  with pytest.raises(ValueError, match="needs ego features"):
    sampling.predict_batch(
        bundle(g, p, cfg, film),
        jnp.arange(2),
        jnp.zeros(2),
        jnp.full(2, 30.0),
        jnp.zeros(2),
        keys,
        schedule=diffusion.cosine_schedule(),
        config=uncond_only,
    )


def test_ego_residual_adds_the_extrapolated_controls(model):
  g, p = model
  ego = jax.random.normal(jax.random.key(6), (2, ego_motion.NUM_FEATURES))
  keys = jax.random.split(jax.random.key(7), 2)
  token = _predict_ego(g, p, ego, keys, SAMPLING, DenoiserConfig())
  residual = DenoiserConfig(conditioning="ego_residual", residual_decay_s=(1.0, 0.5))
  out = _predict_ego(g, p, ego, keys, SAMPLING, residual)
  base = ego_motion.residual_controls(ego, (1.0, 0.5))[:, None]
  np.testing.assert_allclose(out.controls, token.controls + base, atol=1e-5)
  np.testing.assert_allclose(out.trajectories, vmm.rollout(out.controls, 30.0, 0.0), atol=1e-3)
