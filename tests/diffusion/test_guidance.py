"""Uncertainty-aware cosine CFG against the paper's formulas."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import diffusion
from cvmdx_jax.config.sampling import GuidanceConfig

T = 1000


def paper_w(t, delta, w_min=0.1, w_base=1.0, t_c=50.0):
  w_max = w_base * (1 - min(delta, t_c) / t_c)
  return w_min + (w_max - w_min) * (1 - math.cos(math.pi * t / T)) / 2


@pytest.mark.parametrize(
    "t,delta",
    [(0, 0.0), (T, 0.0), (0, 10.0), (T, 10.0), (500, 25.0), (T, 50.0), (T, 80.0), (300, 70.0)],
)
def test_weight_matches_paper(t, delta):
  w = float(diffusion.guidance_weight(t, delta, T))
  assert w == pytest.approx(paper_w(t, delta), abs=1e-6)


def test_weight_endpoints():
  assert float(diffusion.guidance_weight(0, 3.0, T)) == pytest.approx(0.1)
  assert float(diffusion.guidance_weight(T, 0.0, T)) == pytest.approx(1.0)
  assert float(diffusion.guidance_weight(T, 10.0, T)) == pytest.approx(0.8)
  # delta >= t_c: w_max = 0, so w falls from w_min at t = 0 to 0 at t = T
  for delta in (50.0, 51.0, 1e3):
    assert float(diffusion.guidance_weight(T, delta, T)) == pytest.approx(0.0, abs=1e-7)
  official = GuidanceConfig(direction="official")
  assert float(diffusion.guidance_weight(T, 0.0, T, official)) == pytest.approx(0.1)
  assert float(diffusion.guidance_weight(0, 0.0, T, official)) == pytest.approx(1.0)


def test_combine_forms():
  c, u = jnp.full((2, 3), 2.0), jnp.full((2, 3), 1.0)
  np.testing.assert_allclose(diffusion.combine_eps(c, u, jnp.zeros(2)), c)
  np.testing.assert_allclose(diffusion.combine_eps(c, u, jnp.full(2, 0.5)), 2.5)
  np.testing.assert_allclose(diffusion.combine_eps(c, u, jnp.full(2, 0.5), "official"), 1.5)
  np.testing.assert_allclose(diffusion.combine_eps(c, u, jnp.ones(2), "official"), c)
  with pytest.raises(ValueError, match="form"):
    GuidanceConfig(form="other")


def _toy_model(x_t, t, cond):
  return x_t * (1.0 + 0.1 * cond[:, None, None]) + 0.01 * t[:, None, None]


@pytest.mark.parametrize("form", ["paper", "official"])
def test_guided_v_equals_eps_space_combination(form):
  schedule = diffusion.cosine_schedule(T)
  cfg = GuidanceConfig(form=form)
  x_t = jax.random.normal(jax.random.key(0), (4, 125, 2))
  t = jnp.array([999, 600, 100, 0])
  cond, null, delta = jnp.array([1, 2, 3, 4]), 9, jnp.array([0.0, 5.0, 30.0, 80.0])
  v = diffusion.guided_v_fn(_toy_model, cond, null, delta, schedule, cfg)(x_t, t)
  abar = schedule.alphas_cumprod[t]
  w = diffusion.guidance_weight(t, delta, T, cfg)
  eps = diffusion.guided_eps(
      _toy_model(x_t, t, cond), _toy_model(x_t, t, jnp.full(4, null)), x_t, abar, w, form
  )
  np.testing.assert_allclose(diffusion.eps_from_v(x_t, v, abar), eps, atol=1e-4)


@pytest.mark.parametrize("form,kept", [("paper", "cond"), ("official", "null")])
def test_zero_weight_runs_the_one_branch_the_combination_keeps(form, kept):
  """w = 0 everywhere: "paper" (1 + 0) c - 0 u = c, "official" u + 0 (c - u) = u, from one
  model call of B rows, equal bit for bit to the combination of both branches."""
  schedule = diffusion.cosine_schedule(T)
  cfg = GuidanceConfig(w_min=0.0, w_max_base=0.0, form=form)
  assert cfg.off and not GuidanceConfig(w_min=0.0).off
  x_t = jax.random.normal(jax.random.key(1), (3, 125, 2))
  t, cond, null = jnp.array([10, 500, 990]), jnp.array([0, 1, 2]), 5
  rows = []
  model = lambda x, tt, c: rows.append(len(x)) or _toy_model(x, tt, c)
  v = diffusion.guided_v_fn(model, cond, null, jnp.zeros(3), schedule, cfg)(x_t, t)
  assert rows == [3]
  want = _toy_model(x_t, t, cond if kept == "cond" else jnp.full(3, null))
  np.testing.assert_array_equal(v, want)
  pair = diffusion.combine_eps(
      _toy_model(x_t, t, cond), _toy_model(x_t, t, jnp.full(3, null)), jnp.zeros(3), form
  )
  np.testing.assert_array_equal(v, pair)
