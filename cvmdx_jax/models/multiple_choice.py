"""A multiple-choice MLP: K trajectory hypotheses and their probabilities (beyond the paper).

The learned baseline that cVMDx is judged against on the same inputs as its denoiser
(`diffusion.conditioning` "ego_film_residual"): the scenario token q (a learned
embedding), its uncertainty delta (as log(1 + delta)) and the ego-motion + neighbour
features of `cvmdx_jax.ego_motion`. An MLP maps them to K heads of normalised controls
(125, 2) and K mode logits. Each head's controls are, as for the denoiser, the residual
to the ego's extrapolated current controls (`ego_motion.residual_controls`) in units of
`control_scale`, and are rolled out with the VMM from (v0, psi0): every hypothesis is a
trajectory the vehicle motion model can drive, it starts with the ego's speed and
heading, and a head that outputs 0 is the decayed constant-acceleration extrapolation.

Functional form (`cvmdx_jax.models.functional`): `init` -> (graphdef, params),
`apply(graphdef, params, ...)` merges them. `hypotheses` gives (trajectories (B, K, 125,
2) m, probabilities (B, K)).
"""

import jax
import jax.numpy as jnp
from flax import nnx

from cvmdx_jax import constants, ego_motion, targets, vmm
from cvmdx_jax.config.models import MultipleChoiceConfig
from cvmdx_jax.models import functional

OUTPUT_INIT_SCALE = 1e-2  # variance scale of the control heads' init: heads start near
# the residual base, yet differ, so that winner-takes-all assigns them different scenarios


class MultipleChoiceMLP(nnx.Module):
  """(q, delta, ego) -> (K normalised residual controls (B, K, 125, 2), K logits (B, K))."""

  def __init__(self, config: MultipleChoiceConfig, *, rngs: nnx.Rngs):
    self.config = config
    self.token_embed = nnx.Embed(config.num_tokens, config.token_dim, rngs=rngs)
    widths = (config.input_dim, *config.hidden)
    self.layers = nnx.List([nnx.Linear(a, b, rngs=rngs) for a, b in zip(widths, widths[1:])])
    out_init = nnx.initializers.variance_scaling(OUTPUT_INIT_SCALE, "fan_in", "normal")
    self.controls = nnx.Linear(
        widths[-1], config.num_hypotheses * constants.T_PRED * 2, kernel_init=out_init, rngs=rngs
    )
    self.logits = nnx.Linear(widths[-1], config.num_hypotheses, rngs=rngs)

  def __call__(self, q, delta, ego):
    return self.heads(self.features(q, delta, ego))

  def features(self, q, delta, ego):
    """The last hidden layer (B, hidden[-1]) of q (B,), delta (B,), ego (B, F)."""
    h = jnp.concatenate(
        [ego, jnp.log1p(jnp.maximum(delta, 0.0))[:, None], self.token_embed(q)], axis=-1
    )
    for layer in self.layers:
      h = jax.nn.gelu(layer(h))
    return h

  def heads(self, h):
    """(controls (B, K, 125, 2), logits (B, K)) of the hidden features h (B, hidden[-1])."""
    controls = self.controls(h).reshape(len(h), self.config.num_hypotheses, constants.T_PRED, 2)
    return controls, self.logits(h)


def init(config: MultipleChoiceConfig, key: jax.Array) -> tuple[nnx.GraphDef, dict]:
  """(graphdef, params), params a pure dict."""
  return functional.init(lambda rngs: MultipleChoiceMLP(config, rngs=rngs), key)


def make_graphdef(config: MultipleChoiceConfig) -> nnx.GraphDef:
  """The graph definition alone (no parameters are allocated)."""
  return functional.make_graphdef(MultipleChoiceMLP, config)


def abstract_params(config: MultipleChoiceConfig) -> dict:
  """The parameters' shapes and dtypes (`jax.ShapeDtypeStruct`s; nothing is allocated)."""
  return functional.abstract_params(MultipleChoiceMLP, config)


def apply(graphdef, params, q, delta, ego):
  """Raw outputs: q (B,) int, delta (B,), ego (B, F) -> (controls (B, K, 125, 2) in units
  of `control_scale`, residual to the base; logits (B, K))."""
  return nnx.merge(graphdef, params)(q, delta, ego)


def rollout(config: MultipleChoiceConfig, controls, ego, v0, psi0):
  """Trajectories of the heads' outputs.

  Args:
    config: the model's config (control scale, residual base).
    controls: (B, K, 125, 2) normalised residual controls (`apply`).
    ego: (B, F) ego-motion features; v0, psi0: (B,) speed m/s and heading rad at t0.

  Returns:
    (B, K, 125, 2) positions after t0, m.
  """
  base = ego_motion.residual_controls(ego, config.residual_decay_s)[:, None]
  physical = base + targets.denormalize_controls(controls, config.control_scale)
  return vmm.rollout(physical, v0[:, None], psi0[:, None])


def hypotheses(graphdef, params, config: MultipleChoiceConfig, q, delta, ego, v0, psi0):
  """(trajectories (B, K, 125, 2) m, probabilities softmax(logits) (B, K)); see `apply`."""
  controls, logits = apply(graphdef, params, q, delta, ego)
  return rollout(config, controls, ego, v0, psi0), jax.nn.softmax(logits, axis=-1)
