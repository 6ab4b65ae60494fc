"""The inference path: (a `bundles.Denoiser`, tokens q, delta, v0, psi0, keys[, ego
features]) -> N sampled control sequences, their trajectories, the mean trajectory and
the hypotheses. Plain jittable code: the caller jits at its boundary (`predictor.Predictor`;
`jax.jit(predict_batch, static_argnames=STATIC_ARGNAMES)` for a batch alone).

Each scenario draws its noise from its own key, so a scenario's samples do not
depend on which other scenarios share the batch.
"""

import dataclasses

import jax
import jax.numpy as jnp

from cvmdx_jax import constants, ego_motion, targets, vmm
from cvmdx_jax.config.sampling import SamplingConfig, check_sampling
from cvmdx_jax.diffusion import (
    Schedule,
    cond_uncond_v_fn,
    get_sampler,
    guidance_weight,
    guided_v_fn,
    official_ddim_sample,
)
from cvmdx_jax.diffusion.distillation import student_cond
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference.bundles import Denoiser
from cvmdx_jax.models.unet1d import apply_intent, apply_unet
from cvmdx_jax.multimodal import Hypotheses, fit_hypotheses

# of `predict_batch` under jax.jit
STATIC_ARGNAMES = ("config",)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Prediction:
  """Predictions for B scenarios.

  Attributes:
    controls: (B, N, 125, 2) sampled [a_x m/s^2, yaw_rate rad/s].
    trajectories: (B, N, 125, 2) positions in metres (scenario frame).
    mean: (B, 125, 2) the sample mean trajectory.
    hypotheses: `Hypotheses` (means (B, c_max, 125, 2), probs (B, c_max), ...).
  """

  controls: jax.Array
  trajectories: jax.Array
  mean: jax.Array
  hypotheses: Hypotheses


def sample_controls(
    graphdef,
    params,
    q,
    delta,
    key,
    *,
    schedule: Schedule,
    null_token: int,
    config: SamplingConfig,
    ego=None,
    guidance_input: bool = False,
):
  """N normalised control samples for one scenario: q, delta scalars -> (N, 125, 2).

  ego: (F,) ego-motion features for a U-Net with cond_dim = F, or (N, F) one row a sample
  (an intent conditioning's drawn class), else None. Both guidance branches get them: the
  unconditional branch drops only the token (the paper's CFG).
  guidance_input: the U-Net is a guidance student (its last FiLM feature is w(t, delta)):
  one evaluation per step replaces the guided pair.
  """
  n = config.num_samples
  if ego is not None:
    ego = jnp.broadcast_to(ego, (n, ego.shape[-1]))
  # the guided pair evaluates 2N rows: each sample's features twice
  cond = lambda x_t: None if ego is None else jnp.tile(ego, (len(x_t) // n, 1))
  model_fn = lambda x_t, t, c: apply_unet(graphdef, params, x_t, t, c, cond=cond(x_t))
  shape = (n, constants.T_PRED, 2)
  if guidance_input:
    qs = jnp.full((n,), q)
    v_fn = lambda x_t, t: apply_unet(
        graphdef,
        params,
        x_t,
        t,
        qs,
        cond=student_cond(
            cond(x_t), guidance_weight(t, delta, schedule.num_steps, config.guidance)
        ),
    )
    return _sample(v_fn, key, shape, schedule, config)
  if config.mode == "official":
    return official_ddim_sample(
        cond_uncond_v_fn(model_fn, jnp.full((n,), q), null_token),
        key,
        shape,
        schedule,
        steps=config.steps,
        eta=config.eta,
        clip_x0=config.clip_x0,
        w_start=config.guidance.w_min,
        w_end=config.guidance.w_max_base,
    )
  v_fn = guided_v_fn(
      model_fn, jnp.full((n,), q), null_token, jnp.full((n,), delta), schedule, config.guidance
  )
  return _sample(v_fn, key, shape, schedule, config)


def _sample(v_fn, key, shape, schedule: Schedule, config: SamplingConfig):
  """x0 samples of `shape` from the guided `v_fn` with the sampler of `config`."""
  sample = get_sampler(config.sampler, steps=config.steps, eta=config.eta, clip_x0=config.clip_x0)
  return sample(v_fn, key, shape, schedule)


def draw_intents(logits, key, n: int):
  """n maneuver classes (n,) int drawn from softmax(logits) (C,) by systematic sampling
  (one uniform offset, n evenly spaced points on the cumulative probabilities): class c
  gets n p_c samples, up to one, in class order."""
  u = (jnp.arange(n) + jax.random.uniform(key)) / n
  cdf = jnp.cumsum(jax.nn.softmax(logits))
  return jnp.minimum(jnp.searchsorted(cdf, u, side="right"), logits.shape[-1] - 1)


def predict_batch(
    denoiser: Denoiser,
    q,
    delta,
    v0,
    psi0,
    keys,
    ego=None,
    *,
    schedule: Schedule,
    config: SamplingConfig = SamplingConfig(),
) -> Prediction:
  """Samples, rolls out and clusters predictions for B scenarios.

  Args:
    denoiser: the trained `Denoiser` bundle (its U-Net, null token Q and `DenoiserConfig`:
      control scale, conditioning, residual decay).
    q: (B,) int scenario tokens.
    delta: (B,) Mahalanobis uncertainty of each scenario.
    v0: (B,) ego speed at t0, m/s.
    psi0: (B,) ego heading at t0, rad.
    keys: (B,) PRNG keys, one per scenario.
    ego: (B, F) `ego_motion.ego_features`; required unless the conditioning is "token".
    schedule: the diffusion `Schedule` the model was trained with.
    config: `SamplingConfig`.

  Returns:
    `Prediction`.
  """
  graphdef, params = denoiser.graphdef, denoiser.params
  denoiser_config = denoiser.config.diffusion
  check_sampling(config, denoiser_config)
  conditioning = denoiser_config.conditioning
  if conditioning != "token" and ego is None:
    raise UserError(f"predict_batch: conditioning {conditioning!r} needs ego features")
  film = ego if ego_motion.uses_film(conditioning) else None
  if denoiser_config.intent_conditioning:
    keys, intent_keys = jnp.moveaxis(jax.vmap(jax.random.split)(keys), 1, 0)
    logits = apply_intent(graphdef, params, ego) + jnp.log(jnp.asarray(config.intent_prior))
    intents = jax.vmap(draw_intents, (0, 0, None))(logits, intent_keys, config.num_samples)
    film = jnp.concatenate(
        [
            jnp.broadcast_to(ego[:, None], intents.shape + ego.shape[-1:]),
            jax.nn.one_hot(intents, logits.shape[-1], dtype=ego.dtype),
        ],
        -1,
    )
  x0 = jax.vmap(
      lambda qi, di, ki, ei: sample_controls(
          graphdef,
          params,
          qi,
          di,
          ki,
          schedule=schedule,
          null_token=denoiser.null_token,
          config=config,
          ego=ei,
          guidance_input=denoiser_config.guidance_input,
      )
  )(q, delta, keys, film)
  controls = targets.denormalize_controls(x0, denoiser_config.control_scale)
  if ego_motion.uses_residual(conditioning):
    controls = (
        controls + ego_motion.residual_controls(ego, denoiser_config.residual_decay_s)[:, None]
    )
  trajectories = vmm.rollout(controls, v0[:, None], psi0[:, None])
  return Prediction(
      controls=controls,
      trajectories=trajectories,
      mean=jnp.mean(trajectories, axis=1),
      hypotheses=fit_hypotheses(trajectories, config=config.hypotheses),
  )
