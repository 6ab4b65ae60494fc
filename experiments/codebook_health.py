"""Codebook health: entries in use and perplexity of CVQ vs VQ for several codebook sizes.

  .venv/bin/python experiments/codebook_health.py \
      --config=configs/tokenizer.py:demo --workdir=runs/codebook_health

Trains one tokeniser per (Q, quantizer) with the same config, data, seed and number of
steps (only `quantizer.codebook_size` and `.kind` change) into <workdir>/<quantizer>_q<Q>, and
writes a Markdown table of entries in use (training scenarios per entry >= 1), their
share of Q, perplexity of the token distribution over the training split, the
maneuver accuracy on the training split, the number of steps, and how much the tokens
tell about the future: ADE / FDE on the test split of the token-mean baseline (each
token's mean training controls rolled out from the scenario's own state,
`baselines.token_mean`) next to constant velocity, to <workdir>/codebook_health.md.
Finished runs are reused (each run resumes from its own workdir).
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import json
from pathlib import Path

from absl import app, flags, logging
from ml_collections import config_flags

from cvmdx_jax.config.runs import TokenizerRunConfig
from cvmdx_jax.data import dataset
from cvmdx_jax.evaluation import baselines, metrics
from cvmdx_jax.models import quantizer as quantizer_lib
from cvmdx_jax.runs import tokens
from cvmdx_jax.storage import atomic
from cvmdx_jax.train import tokenizer

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Tokeniser config file, e.g. configs/tokenizer.py:demo.", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory (one run per row).")
_SIZES = flags.DEFINE_list(
    "codebook_sizes", ["30", "60", "90", "128", "256"], "Codebook sizes Q to compare."
)
flags.mark_flags_as_required(["config", "workdir"])
cli.output_dirs("workdir")
cli.int_list("codebook_sizes", 1)
cli.typed_config("config", TokenizerRunConfig.from_config)  # checked; rows vary Q and kind


def _errors(pred, test) -> str:
  """'ADE | FDE' in metres of (M, 125, 2) predictions on the test split."""
  return (
      f"{float(metrics.ade(pred, test.future).mean()):.3f} | "
      f"{float(metrics.fde(pred, test.future).mean()):.3f}"
  )


def _row(run_dir: Path, q: int, kind: str, splits: dict) -> str:
  train, _ = tokens.load_tokens(tokens.tokens_path(run_dir, "train"))
  test, _ = tokens.load_tokens(tokens.tokens_path(run_dir, "test"))
  in_use, perplexity = quantizer_lib.codebook_stats(train.q, q)
  last = json.loads((run_dir / "metrics.jsonl").read_text().splitlines()[-1])
  pred = baselines.token_mean(
      splits["train"].controls, train.q, test.q, splits["test"].v0, splits["test"].psi0, q
  )
  return (
      f"| {q} | {kind} | {int(in_use)} | {100 * int(in_use) / q:.0f} % | "
      f"{float(perplexity):.1f} | {last['train_accuracy']:.3f} | {last['step']} | "
      f"{_errors(pred, splits['test'])} |"
  )


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Too many command-line arguments: {argv[1:]}")
  workdir = Path(_WORKDIR.value)
  config = _CONFIG.value
  splits = {name: dataset.load_split(config.data_dir, name) for name in ("train", "test")}
  cv = baselines.constant_velocity(splits["test"].xi)
  rows = [
      "| Q | quantizer | entries in use | share of Q | perplexity | train acc. | steps | "
      "token-mean ADE [m] | token-mean FDE [m] |",
      "|---|---|---|---|---|---|---|---|---|",
      f"| - | constant velocity | | | | | | {_errors(cv, splits['test'])} |",
  ]
  for q in (int(s) for s in _SIZES.value):
    for kind in ("cvq", "vq"):
      run = config.copy_and_resolve_references()
      run.quantizer.codebook_size, run.quantizer.kind = q, kind
      run_dir = workdir / f"{kind}_q{q}"
      tokenizer.train(TokenizerRunConfig.from_config(run), run_dir)
      rows.append(_row(run_dir, q, kind, splits))
      logging.info("%s", rows[-1])
  table = "\n".join(rows) + "\n"
  print(table)
  atomic.write_text(workdir / "codebook_health.md", table)


if __name__ == "__main__":
  cli.run(main, allocator=True)
