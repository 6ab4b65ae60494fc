"""The learned baseline in a report: the tokeniser check and the per-scenario errors.

A baseline run (`cvmdx_jax.train.baseline`; files in `runs.layout`) is loaded with
`inference.bundles.load_baseline`. Rows of a report (`METHODS`): the most likely head (argmax
p), the probability-weighted mean of the K heads and the best of K (minADE_K / minFDE_K,
Brier-minFDE, ... as for cVMDx's hypotheses).
"""

import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.errors import UserError
from cvmdx_jax.evaluation import metrics, scoring
from cvmdx_jax.inference.bundles import LearnedBaseline, TokenizerBundle
from cvmdx_jax.storage import identity

METHODS = ("mlp_most_likely", "mlp_mean", "mlp_best_of_k")


class IncompatibleBaselineError(UserError):
  """The baseline was trained on tokens of another tokeniser than the one evaluated."""


def check_tokenizer(baseline: LearnedBaseline, tokenizer: TokenizerBundle, where: str) -> None:
  """Refuses a baseline trained on tokens of another tokeniser checkpoint than `tokenizer`.

  Raises:
    IncompatibleBaselineError: naming `where` and the differing keys.
  """
  identity.check(
      baseline.fingerprint.to_dict()["tokenizer"],
      tokenizer.checkpoint.to_dict(),
      f"baseline {where} (not trained on tokens of this tokeniser; retrain it on "
      "this tokeniser's tokens)",
      IncompatibleBaselineError,
  )


def scenario_errors(baseline: LearnedBaseline, q, delta, scenarios) -> dict:
  """Per-scenario errors of the rows `METHODS` on `scenarios` with tokens q (M,) and delta
  (M,) of the evaluated tokeniser (`errors`)."""
  trajectories, probs = baseline(
      q, delta, scenarios.xi, scenarios.mask, scenarios.v0, scenarios.psi0
  )
  return errors(trajectories, probs, scenarios.future, scenarios.label)


def errors(trajectories, probs, gt, labels) -> dict:
  """Per-scenario errors of the rows `METHODS`: trajectories (M, K, T, 2), probs (M, K),
  gt (M, T, 2), labels (M,) -> {method: {metric: (M,)}} (`scoring` metrics)."""
  trajectories, probs, gt = (jnp.asarray(a) for a in (trajectories, probs, gt))
  mean = jnp.einsum("mk,mktc->mtc", probs, trajectories, precision=constants.EXACT_MATMUL)
  # every head is a hypothesis: a probability that underflowed to 0 must not drop it
  used = jnp.maximum(probs, jnp.finfo(probs.dtype).tiny)
  return {
      "mlp_most_likely": scoring.single_trajectory_errors(
          metrics.most_likely(trajectories, probs), gt
      ),
      "mlp_mean": scoring.single_trajectory_errors(mean, gt),
      "mlp_best_of_k": scoring.best_of_k_errors(trajectories, used, gt, labels),
  }
