"""Predictions kept on disk: a `Predictor` whose outputs for the same model, inputs and seed
are read back instead of sampled again (the quality benchmark scores one run's predictions
several times)."""

import hashlib
from pathlib import Path

import jax
import numpy as np

from cvmdx_jax.inference.predictor import PredictorOutput
from cvmdx_jax.inference.sampling import Prediction
from cvmdx_jax.multimodal import Hypotheses
from cvmdx_jax.storage import checksums, identity


def model_id(predictor) -> str:
  """What a `Predictor`'s outputs depend on besides its inputs: the tokeniser checkpoint,
  the denoiser's parameters and the sampling settings (a content hash)."""
  return identity.content_id(
      {
          "tokenizer": predictor.tokenizer.checkpoint.to_dict(),
          "denoiser": jax.tree.map(np.asarray, predictor.denoiser.params),
          "sampling": repr(predictor.sampling),
      }
  )


def cached(predictor, cache_dir: Path, run_name: str, model: str):
  """`predictor` whose outputs are kept in cache_dir, keyed by `model` (`model_id`), the
  inputs and the seed (controls are not kept: None)."""

  def predict(scenarios, seed):
    digest = hashlib.sha256(model.encode() + np.asarray(scenarios.xi, np.float32).tobytes())
    digest.update(np.asarray(scenarios.mask, bool).tobytes() + str(seed).encode())
    path = cache_dir / f"{run_name}_{digest.hexdigest()[:16]}.npz"
    if not path.is_file():
      out = predictor(scenarios, seed=seed)
      hyp = out.hypotheses
      fields = {
          "trajectories": out.prediction.trajectories,
          "hyp_means": hyp.means,
          "hyp_probs": hyp.probs,
          "hyp_labels": hyp.labels,
          "q": out.q,
          "delta": out.delta,
      }
      arrays = {k: np.asarray(v) for k, v in fields.items()}
      cache_dir.mkdir(parents=True, exist_ok=True)
      checksums.write_all({path: checksums.npz_bytes(**arrays)})
    with np.load(path) as z:
      probs, traj = z["hyp_probs"], z["trajectories"]
      num = np.sum(probs > 0, axis=1)
      hyp = Hypotheses(
          num, num, z["hyp_labels"], z["hyp_means"], probs, np.full(probs.shape, np.nan)
      )
      delta = z["delta"]
      return PredictorOutput(
          Prediction(None, traj, traj.mean(axis=1), hyp),
          z["q"],
          delta,
          ~(delta <= predictor.delta_limit),
      )

  return predict
