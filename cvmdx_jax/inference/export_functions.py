"""The two functions an export traces and their signatures: `predict_fn` (the whole
prediction of a `Predictor`, inputs `predict_inputs`, outputs `PREDICT_OUTPUTS`) and
`denoiser_fn` (one evaluation of its prepared denoiser, inputs `denoiser_inputs`); shapes
hold `BATCH`, the symbolic batch dimension (`inference.export` writes them)."""

import functools

import jax

from cvmdx_jax import constants
from cvmdx_jax.diffusion import cosine_schedule
from cvmdx_jax.inference import predictor as predictor_lib

BATCH = "b"  # the symbolic batch dimension's name in shapes and the manifest


def predict_inputs(num_noise_ids: int = 1) -> tuple:
  """(name, shape with BATCH, dtype) of predict.jax's positional inputs."""
  return (
      ("xi", (BATCH, constants.NUM_VEHICLES, constants.T_OBS, 4), "float32"),
      ("mask", (BATCH, constants.NUM_VEHICLES, constants.T_OBS), "bool"),
      ("v0", (BATCH,), "float32"),
      ("psi0", (BATCH,), "float32"),
      ("seed", (), "uint32"),
      ("noise_ids", (BATCH, num_noise_ids), "uint32"),
  )


PREDICT_OUTPUTS = (
    "trajectories",
    "controls",
    "mean",
    "hypothesis_means",
    "hypothesis_probs",
    "num_modes",
    "labels",
    "q",
    "delta",
)


def _keys(seed, noise_ids):
  """(b,) PRNG keys of `noise_ids` (b, K), those of `Predictor.__call__`."""
  return jax.vmap(functools.partial(predictor_lib._fold_ids, jax.random.key(seed)))(noise_ids)


def predict_fn(predictor: predictor_lib.Predictor):
  """f(xi, mask, v0, psi0, seed, noise_ids) -> {name: array} of `PREDICT_OUTPUTS`: trajectories
  and controls (b, N, 125, 2), mean (b, 125, 2), hypothesis_means (b, C_max, 125, 2),
  hypothesis_probs (b, C_max), num_modes (b,), labels (b, N), q (b,), delta (b,); the
  predictor's parameters are closed over (constants once exported)."""
  schedule = cosine_schedule(predictor.denoiser.config.diffusion.num_steps)

  def f(xi, mask, v0, psi0, seed, noise_ids):
    pred, q, delta = predictor_lib._predict(
        predictor.tokenizer,
        predictor.denoiser,
        xi,
        mask,
        v0,
        psi0,
        _keys(seed, noise_ids),
        schedule,
        config=predictor.sampling,
    )
    hyp = pred.hypotheses
    return {
        "trajectories": pred.trajectories,
        "controls": pred.controls,
        "mean": pred.mean,
        "hypothesis_means": hyp.means,
        "hypothesis_probs": hyp.probs,
        "num_modes": hyp.num_modes,
        "labels": hyp.labels,
        "q": q,
        "delta": delta,
    }

  return f


def cond_dim(predictor: predictor_lib.Predictor) -> int:
  """Width of the denoiser's FiLM input (0: none): ego features, the drawn intent's
  one-hot, then w for a guidance student (`diffusion.distillation.student_cond`)."""
  return predictor.denoiser.config.model.cond_dim


def denoiser_fn(predictor: predictor_lib.Predictor):
  """f(x_t (b, 125, 2) f32, t (b,) int32, q (b,) int32[, cond (b, cond_dim) f32]) -> v
  (b, 125, 2): one evaluation of the prepared denoiser."""
  denoiser = predictor.denoiser
  if cond_dim(predictor):
    return lambda x_t, t, q, cond: denoiser.apply(x_t, t, q, cond)
  return lambda x_t, t, q: denoiser.apply(x_t, t, q)


def denoiser_inputs(predictor: predictor_lib.Predictor) -> tuple:
  """(name, shape, dtype) of denoiser.jax's inputs."""
  inputs = (
      ("x_t", (BATCH, constants.T_PRED, 2), "float32"),
      ("t", (BATCH,), "int32"),
      ("q", (BATCH,), "int32"),
  )
  c = cond_dim(predictor)
  return inputs + ((("cond", (BATCH, c), "float32"),) if c else ())


def abstract_inputs(inputs, batch) -> list:
  """`jax.ShapeDtypeStruct`s of (name, shape, dtype) `inputs`, BATCH set to `batch`."""
  return [
      jax.ShapeDtypeStruct(tuple(batch if d == BATCH else d for d in shape), dtype)
      for _, shape, dtype in inputs
  ]
