"""The codebook-size ablation of the paper's Table I on a chosen dataset.

  .venv/bin/python experiments/ablate_codebook.py --data_dir=runs/demo/data \\
      --workdir=runs/ablation --codebook_sizes=30,60,90,128,256 \\
      --tokenizer_preset=demo --diffusion_preset=demo [--quantizers=cvq,vq]

For every (quantizer, Q): trains the tokeniser and the diffusion model (resuming
finished runs), evaluates on the test split, and writes `<workdir>/ablation.md` (mean,
most likely p(c) and best-of-K ADE / FDE per row) and `<workdir>/ablation.json`.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

from pathlib import Path

from absl import app, flags

from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.runs import DiffusionRunConfig, TokenizerRunConfig
from cvmdx_jax.evaluation import report
from cvmdx_jax.storage import atomic
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import tokenizer as tokenizer_train

_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory (make_dataset output).")
_WORKDIR = flags.DEFINE_string("workdir", None, "Where runs and the table go.")
_SIZES = flags.DEFINE_list("codebook_sizes", ["30", "60", "90", "128", "256"], "Q values.")
_QUANTIZERS = flags.DEFINE_list("quantizers", ["cvq"], "cvq and/or vq.")
_TOK = flags.DEFINE_string("tokenizer_preset", "demo", "configs/tokenizer.py preset.")
_DIFF = flags.DEFINE_string("diffusion_preset", "demo", "configs/diffusion.py preset.")
_MAX = flags.DEFINE_integer(
    "max_scenarios", 0, "Class-balanced test subset (0 = all).", lower_bound=0
)
flags.mark_flags_as_required(["data_dir", "workdir"])
cli.input_dirs("data_dir")
cli.output_dirs("workdir")
cli.int_list("codebook_sizes", 1)
cli.presets("tokenizer_preset", tokenizer_config.get_config)
cli.presets("diffusion_preset", diffusion_config.get_config)
flags.register_validator(
    "quantizers", lambda v: set(v) <= {"cvq", "vq"}, "expected cvq and/or vq, comma-separated"
)
READOUTS = ("cvmdx_mean", "cvmdx_most_likely", "cvmdx_best_of_k")


def run_one(root: Path, data_dir: str, quantizer: str, q: int) -> dict:
  """Trains and evaluates one (quantizer, Q); returns its metrics.json content."""
  run = root / f"{quantizer}_q{q}"
  tok = tokenizer_config.get_config(_TOK.value)
  tok.data_dir, tok.quantizer.codebook_size, tok.quantizer.kind = data_dir, q, quantizer
  tokenizer_train.train(TokenizerRunConfig.from_config(tok), run / "tokenizer")
  diff = diffusion_config.get_config(_DIFF.value)
  diff.data_dir, diff.tokenizer_dir = data_dir, str(run / "tokenizer")
  diffusion_train.train(DiffusionRunConfig.from_config(diff), run / "diffusion")
  return report.run(
      tokenizer_dir=run / "tokenizer",
      diffusion_dir=run / "diffusion",
      data_dir=data_dir,
      workdir=run / "eval",
      max_scenarios=_MAX.value,
      ddpm_scenarios=0,
      figures_per_class=0,
  )


def table(rows: dict) -> str:
  head = "| quantizer | Q | " + " | ".join(f"{r} ADE | {r} FDE" for r in READOUTS) + " |"
  lines = [head, "|---|---|" + "---|---|" * len(READOUTS)]
  for (quantizer, q), results in rows.items():
    cells = " | ".join(
        f"{results[r]['all']['ade']:.2f} | {results[r]['all']['fde']:.2f}" for r in READOUTS
    )
    lines.append(f"| {quantizer} | {q} | {cells} |")
  return "\n".join(lines) + "\n"


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  root = Path(_WORKDIR.value)
  rows = {
      (quantizer, int(q)): run_one(root, _DATA.value, quantizer, int(q))
      for quantizer in _QUANTIZERS.value
      for q in _SIZES.value
  }
  root.mkdir(parents=True, exist_ok=True)
  text = table(rows)
  atomic.write_text(root / "ablation.md", text)
  atomic.write_json(
      root / "ablation.json",
      {f"{k}_q{q}": {r: v[r] for r in READOUTS} for (k, q), v in rows.items()},
  )
  print(text)


if __name__ == "__main__":
  cli.run(main, allocator=True)
