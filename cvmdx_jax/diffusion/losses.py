"""The v-prediction loss with conditioning dropout (for classifier-free guidance)."""

import jax
import jax.numpy as jnp

from cvmdx_jax.diffusion import param
from cvmdx_jax.diffusion.schedule import Schedule


def v_loss(
    model_fn,
    x0,
    cond,
    key,
    schedule: Schedule,
    *,
    null_cond: int,
    cond_drop_prob: float = 0.1,
    weight=None,
):
  """E_{t, eps} ||v - v_theta(x_t, t, c)||^2 with c -> null with probability p.

  Args:
    model_fn: (x_t (B, ...), t (B,), cond (B,)) -> v (B, ...).
    x0: (B, ...) clean (normalised) targets.
    cond: (B,) int condition tokens.
    key: PRNG key.
    schedule: `Schedule`.
    null_cond: the token that stands for "no condition".
    cond_drop_prob: probability of replacing a token by `null_cond`.
    weight: (B,) per-example weights (0 for padding rows); None = all ones.

  Returns:
    Scalar loss: the weighted mean over examples of the per-element mean squared error.
  """
  b = x0.shape[0]
  k_t, k_eps, k_drop = jax.random.split(key, 3)
  t = jax.random.randint(k_t, (b,), 0, schedule.num_steps)
  eps = jax.random.normal(k_eps, x0.shape, x0.dtype)
  abar = schedule.alphas_cumprod[t]
  x_t = param.q_sample(x0, eps, abar)
  drop = jax.random.bernoulli(k_drop, cond_drop_prob, (b,))
  cond = jnp.where(drop, null_cond, cond)
  return weighted_mse(model_fn(x_t, t, cond), param.v_from_x0_eps(x0, eps, abar), weight)


def weighted_mse(pred, target, weight=None):
  """The weighted mean over examples of the per-element mean squared error.

  Args:
    pred, target: (B, ...).
    weight: (B,) per-example weights (0 for padding rows); None = all ones.
  """
  b = pred.shape[0]
  return weighted_mean(jnp.mean(((pred - target) ** 2).reshape(b, -1), axis=-1), weight)


def weighted_mean(per_example, weight=None):
  """sum(weight * per_example) / max(sum(weight), 1): per_example, weight (B,) (0 for
  padding rows); None = all ones."""
  weight = jnp.ones_like(per_example) if weight is None else weight
  return jnp.sum(weight * per_example) / jnp.maximum(jnp.sum(weight), 1.0)
