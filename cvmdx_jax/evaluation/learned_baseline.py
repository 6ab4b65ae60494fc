"""The learned baseline in a report: its run directory, predictions and per-scenario errors.

A baseline run (`cvmdx_jax.train.baseline`):

    <dir>/baseline.json          {"model": MultipleChoiceConfig fields, "fingerprint": ...}
    <dir>/config.json            the run's ConfigDict
    <dir>/checkpoints/<epoch>/   train state; inference reads only "best" (the val choice)
    <dir>/metrics.jsonl          train loss and the val curve per epoch

Both JSON files are checksummed (`cvmdx_jax.checksums`). Rows of a report (`METHODS`):
the most likely head (argmax p), the probability-weighted mean of the K heads and the
best of K (minADE_K / minFDE_K, Brier-minFDE, ... as for cVMDx's hypotheses).
"""

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from cvmdx_jax import checkpointing, checksums, ego_motion, metrics, runs, sharding
from cvmdx_jax.checkpointing import CheckpointMismatchError
from cvmdx_jax.checksums import CorruptRunError
from cvmdx_jax.config_dataclass import to_dataclass
from cvmdx_jax.evaluation import scoring
from cvmdx_jax.models import multiple_choice as mc

BASELINE_JSON = "baseline.json"
METHODS = ("mlp_most_likely", "mlp_mean", "mlp_best_of_k")


class IncompatibleBaselineError(ValueError):
  """The baseline was trained on tokens of another tokeniser than the one evaluated."""


def _read(path: Path) -> dict:
  if not path.is_file():
    raise FileNotFoundError(f"{path}: missing; not a baseline run directory (train one "
                            "with experiments/train_baseline.py)")
  value = checksums.read_json(path)
  if not isinstance(value, dict) or not {"model", "fingerprint"} <= set(value):
    raise CorruptRunError(f"{path}: expected an object with 'model' and 'fingerprint'")
  return value


def check_run_dir(workdir: str | os.PathLike, fingerprint: dict) -> None:
  """Checks (writing nothing) that <workdir>/baseline.json, if any, has `fingerprint`.

  Raises:
    CheckpointMismatchError: the directory holds a baseline run of another fingerprint.
    CorruptRunError: baseline.json is corrupt.
  """
  path = Path(workdir) / BASELINE_JSON
  if path.is_file():
    checkpointing.check_metadata(_read(path)["fingerprint"], checkpointing.to_json(fingerprint),
                                 str(workdir))


def write_run_dir(workdir: str | os.PathLike, config: ml_collections.ConfigDict,
                  model_cfg: mc.MultipleChoiceConfig, fingerprint: dict) -> None:
  """Writes <workdir>/baseline.json and config.json (after `check_run_dir`)."""
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  checksums.write_json(workdir / BASELINE_JSON,
                       {"model": dataclasses.asdict(model_cfg),
                        "fingerprint": checkpointing.to_json(fingerprint)},
                       indent=1, sort_keys=True)
  checksums.write_json(workdir / runs.CONFIG_JSON, json.loads(config.to_json_best_effort()))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LearnedBaseline:
  """A trained multiple-choice MLP for inference (a pytree: only `params` are leaves).

  Attributes:
    params: the parameters of the epoch chosen on val.
    graphdef: the NNX graph definition.
    config: `MultipleChoiceConfig`.
    fingerprint: what it was trained on (`cvmdx_jax.train.baseline.fingerprint`).
    epoch: the chosen epoch.
  """

  params: dict
  graphdef: object = dataclasses.field(metadata={"static": True})
  config: mc.MultipleChoiceConfig = dataclasses.field(metadata={"static": True})
  fingerprint: ml_collections.FrozenConfigDict = dataclasses.field(metadata={"static": True})
  epoch: int = dataclasses.field(default=0, metadata={"static": True})

  def __call__(self, q, delta, xi, mask, v0, psi0):
    """(trajectories (M, K, 125, 2) m, probabilities (M, K)) from tokens q (M,), delta
    (M,) and the observed scenarios xi (M, 9, 75, 4), mask (M, 9, 75), v0, psi0 (M,)."""
    out = _hypotheses(self, jnp.asarray(q, jnp.int32), jnp.asarray(delta, jnp.float32),
                      jnp.asarray(xi, jnp.float32), jnp.asarray(mask, bool),
                      jnp.asarray(v0, jnp.float32), jnp.asarray(psi0, jnp.float32))
    return tuple(np.asarray(a) for a in out)


@jax.jit
def _hypotheses(baseline: LearnedBaseline, q, delta, xi, mask, v0, psi0):
  ego = ego_motion.ego_features(xi, mask)
  return mc.hypotheses(baseline.graphdef, baseline.params, baseline.config, q, delta, ego,
                       v0, psi0)


def load(workdir: str | os.PathLike) -> LearnedBaseline:
  """The val-chosen parameters of a baseline run, for inference.

  Raises:
    FileNotFoundError: no baseline.json (not a baseline run directory).
    CorruptRunError: baseline.json is corrupt.
    CheckpointMismatchError: no complete checkpoint, another model size or fingerprint,
      or a baseline trained on another number of ego-motion features.
  """
  workdir = Path(workdir)
  saved = _read(workdir / BASELINE_JSON)
  model_cfg = to_dataclass(mc.MultipleChoiceConfig, saved["model"])
  if saved["fingerprint"].get("features") != ego_motion.NUM_FEATURES:
    raise CheckpointMismatchError(
        f"{workdir}: the baseline was trained on {saved['fingerprint'].get('features')} "
        f"ego-motion features, this version computes {ego_motion.NUM_FEATURES}; retrain it")
  abstract = jax.eval_shape(lambda k: mc.init(model_cfg, k)[1], jax.random.key(0))
  rep = sharding.replicated(sharding.data_mesh())
  spec = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep)
  abstract = {"best": {"params": jax.tree.map(spec, abstract),
                       "epoch": spec(jax.ShapeDtypeStruct((), jnp.int32))}}
  state, meta = checkpointing.load_latest(workdir / runs.CHECKPOINTS, abstract, partial=True)
  checkpointing.check_metadata(meta.get("fingerprint"), saved["fingerprint"],
                               str(workdir / runs.CHECKPOINTS))
  return LearnedBaseline(state["best"]["params"], mc.make_graphdef(model_cfg), model_cfg,
                         ml_collections.FrozenConfigDict(saved["fingerprint"]),
                         int(state["best"]["epoch"]))


def check_tokenizer(baseline: LearnedBaseline, tokenizer: runs.TokenizerBundle,
                    where: str) -> None:
  """Refuses a baseline trained on tokens of another tokeniser checkpoint than `tokenizer`.

  Raises:
    IncompatibleBaselineError: naming `where` and the differing keys.
  """
  used = checkpointing.to_json(baseline.fingerprint.to_dict())["tokenizer"]
  given = {"fingerprint": checkpointing.to_json(tokenizer.fingerprint.to_dict()),
           **(tokenizer.checkpoint or {})}
  differing = sorted(k for k in used if used[k] is not None and used[k] != given.get(k))
  if differing or baseline.config.num_tokens != tokenizer.config.quantizer.codebook_size:
    raise IncompatibleBaselineError(
        f"baseline {where} was not trained on tokens of this tokeniser: differing "
        f"{differing}, {baseline.config.num_tokens} tokens vs codebook size "
        f"{tokenizer.config.quantizer.codebook_size}; retrain it on this tokeniser's tokens")


def scenario_errors(baseline: LearnedBaseline, q, delta, scenarios) -> dict:
  """Per-scenario errors of the rows `METHODS` on `scenarios` with tokens q (M,) and delta
  (M,) of the evaluated tokeniser (`errors`)."""
  trajectories, probs = baseline(q, delta, scenarios.xi, scenarios.mask, scenarios.v0,
                                 scenarios.psi0)
  return errors(trajectories, probs, scenarios.future, scenarios.label)


def errors(trajectories, probs, gt, labels) -> dict:
  """Per-scenario errors of the rows `METHODS`: trajectories (M, K, T, 2), probs (M, K),
  gt (M, T, 2), labels (M,) -> {method: {metric: (M,)}} (`scoring` metrics)."""
  trajectories, probs, gt = (jnp.asarray(a) for a in (trajectories, probs, gt))
  mean = jnp.einsum("mk,mktc->mtc", probs, trajectories)
  # every head is a hypothesis: a probability that underflowed to 0 must not drop it
  used = jnp.maximum(probs, jnp.finfo(probs.dtype).tiny)
  return {"mlp_most_likely": scoring.single_trajectory_errors(
              metrics.most_likely(trajectories, probs), gt),
          "mlp_mean": scoring.single_trajectory_errors(mean, gt),
          "mlp_best_of_k": scoring.best_of_k_errors(trajectories, used, gt, labels)}
