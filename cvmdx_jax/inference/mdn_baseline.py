"""The trained mixture density baseline for inference: `load_mdn(workdir)` ->
`MixtureDensityBaseline`, called like the multiple-choice baseline's `LearnedBaseline`
but returning the predictive distribution, an `inference.distributions.GaussianMixture`.

    mdn = load_mdn("runs/demo/mdn")
    mixture = mdn(q, delta, scenarios.xi, scenarios.mask, scenarios.v0, scenarios.psi0)

Only the val-chosen parameters are restored (`runs.loaders.load_val_chosen`); nothing
from `cvmdx_jax.train` is imported.
"""

import dataclasses
import os

import jax
import ml_collections
import numpy as np
from flax import nnx

from cvmdx_jax import ego_motion
from cvmdx_jax.config.mdn import MDNRunConfig
from cvmdx_jax.inference.bundles import baseline_inputs
from cvmdx_jax.inference.distributions import GaussianMixture
from cvmdx_jax.models import mdn
from cvmdx_jax.runs import loaders


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MixtureDensityBaseline:
  """A trained mixture density network (a pytree: only `params` are leaves).

  Attributes:
    params: the parameters of the epoch with the lowest val mixture NLL.
    graphdef: the NNX graph definition.
    config: the run's `MDNRunConfig` (the network in `config.model`).
    fingerprint: what it was trained on (`train.mdn.fingerprint`; its "tokenizer" entry is
      what `evaluation.learned_baseline.check_tokenizer` compares).
    epoch: the chosen epoch.
  """

  params: dict
  graphdef: nnx.GraphDef = dataclasses.field(metadata={"static": True})
  config: MDNRunConfig = dataclasses.field(metadata={"static": True})
  fingerprint: ml_collections.FrozenConfigDict = dataclasses.field(metadata={"static": True})
  epoch: int = dataclasses.field(default=0, metadata={"static": True})

  def __call__(self, q, delta, xi, mask, v0, psi0) -> GaussianMixture:
    """The mixture (means, stds (M, K, 125, 2) m, weights (M, K), numpy) from tokens q
    (M,), delta (M,) and the observed scenarios xi (M, 9, 75, 4), mask (M, 9, 75), v0,
    psi0 (M,)."""
    out = _mixture(self, *baseline_inputs(q, delta, xi, mask, v0, psi0))
    return jax.tree.map(np.asarray, out)


@jax.jit
def _mixture(model: MixtureDensityBaseline, q, delta, xi, mask, v0, psi0) -> GaussianMixture:
  ego = ego_motion.ego_features(xi, mask)
  means, stds, logits = mdn.mixture(
      model.graphdef, model.params, model.config.model, q, delta, ego, v0, psi0
  )
  return GaussianMixture(means=means, stds=stds, weights=jax.nn.softmax(logits, axis=-1))


def load_mdn(workdir: str | os.PathLike) -> MixtureDensityBaseline:
  """The val-chosen parameters of a mixture density run (`cvmdx_jax.train.mdn`).

  Raises:
    FileNotFoundError: no config.json (not a run directory).
    CorruptRunError: config.json is corrupt.
    CheckpointMismatchError: config.json is not an `MDNRunConfig` of this version (e.g. a
      multiple-choice baseline run); no complete checkpoint, one of another model size, or
      a corrupt one.
  """
  config, params, fingerprint, epoch = loaders.load_val_chosen(
      workdir, MDNRunConfig, mdn.abstract_params, "mixture density"
  )
  return MixtureDensityBaseline(params, mdn.make_graphdef(config.model), config, fingerprint, epoch)
