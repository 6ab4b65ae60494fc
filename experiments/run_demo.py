"""The main job: SUMO data -> CVQ-VAE tokeniser -> diffusion -> distilled student (+ learned
baseline) -> report.

  make demo        (= .venv/bin/python experiments/run_demo.py --workdir=runs/demo)

Writes runs/demo/{data, tokenizer, diffusion, student_*, baseline, mdn}/ and two reports in the
same schema of the last student of `--distill_steps` (the guided denoiser itself where that
is empty), each with the rows of the multiple-choice MLP baseline trained on the same train
split and tokens (`configs/baseline.py`, at most 90 s of the demo; the mixture density
baseline, `configs/mdn.py`, trains beside it in as long): the
test split's (metrics.json, results.md, predictions_<class>.png, kl_vs_usage.png) and
the held-out road's (metrics_test_ood.json, results_test_ood.md, *_test_ood.png; the
single-DDPM baseline there only with `--ood_ddpm_scenarios`). A dataset without a
test_ood split (highD, cvmd_mat) gets the test report only, with a printed note. Every
stage resumes: a rerun reuses the dataset cache and the finished checkpoints. CPU-sized
presets: dataset `:small`, tokeniser `:demo`, diffusion `:demo`, distillation `:demo`,
baseline `:demo` (change them with the flags below).
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import time
from pathlib import Path

from absl import app, flags

from configs import baseline as baseline_config
from configs import dataset as dataset_config
from configs import diffusion as diffusion_config
from configs import distill as distill_config
from configs import mdn as mdn_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.mdn import MDNRunConfig
from cvmdx_jax.config.runs import (
    BaselineRunConfig,
    DiffusionRunConfig,
    DistillRunConfig,
    TokenizerRunConfig,
)
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.data import sumo_plan
from cvmdx_jax.evaluation import animation, report
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.runs import memory
from cvmdx_jax.train import baseline as baseline_train
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import distill as distill_train
from cvmdx_jax.train import mdn as mdn_train
from cvmdx_jax.train import tokenizer as tokenizer_train

_WORKDIR = flags.DEFINE_string("workdir", "runs/demo", "Where everything is written.")
_DATA = flags.DEFINE_string("data_preset", "small", "configs/dataset.py preset.")
_TOKENIZER = flags.DEFINE_string("tokenizer_preset", "demo", "configs/tokenizer.py preset.")
_DIFFUSION = flags.DEFINE_string("diffusion_preset", "demo", "configs/diffusion.py preset.")
_DISTILL = flags.DEFINE_string("distill_preset", "demo", "configs/distill.py preset.")
_DISTILL_STEPS = flags.DEFINE_list(
    "distill_steps",
    [str(s) for s in distill_config.STUDENTS],
    "Students, one run each: a progressive student for the first count of steps taught "
    "by the guided denoiser (guided_progressive), then progressive students, each for "
    "half its teacher's steps; empty: the report samples the guided denoiser.",
)
_BASELINE = flags.DEFINE_string("baseline_preset", "demo", "configs/baseline.py preset.")
_MDN = flags.DEFINE_string("mdn_preset", "demo", "configs/mdn.py preset.")
_SEED = flags.DEFINE_integer(
    "seed",
    0,
    "Training seed of the tokeniser, denoiser, students "
    "and baseline (`config.seed` of each; the data stay the same).",
    lower_bound=0,
)
_DDPM = flags.DEFINE_integer(
    "ddpm_scenarios",
    30,
    "Scenarios of the single-DDPM baseline "
    "on test (1,000 guided steps: ~20 s for 30 on 2 cores).",
    lower_bound=0,
)
_OOD_DDPM = flags.DEFINE_integer(
    "ood_ddpm_scenarios",
    0,
    "Scenarios of the single-DDPM " "baseline on test_ood (0 = none: the demo's time budget).",
    lower_bound=0,
)
cli.output_dirs("workdir")
cli.presets("data_preset", dataset_config.get_config)
cli.presets("tokenizer_preset", tokenizer_config.get_config)
cli.presets("diffusion_preset", diffusion_config.get_config)
cli.presets("distill_preset", distill_config.get_config)
cli.presets("baseline_preset", baseline_config.get_config)
cli.presets("mdn_preset", mdn_config.get_config)
cli.int_list("distill_steps", 1)
flags.register_validator(
    "distill_steps",
    lambda v: all(int(b) * 2 == int(a) for a, b in zip(v, v[1:])),
    "each progressive student takes half its teacher's steps (e.g. 4,2,1)",
)


def _stage(name: str, start: float) -> None:
  """Prints the memory so far (`memory.rss_line`: the peak is the process's, through the stage
  before), hands what the process only kept for reuse back (`memory.release`), then names
  the next stage."""
  print(
      f"    memory: {memory.rss_line()}; released ({memory.release()}): " f"{memory.rss_line()}",
      flush=True,
  )
  print(f"\n=== {name}  (t = {time.perf_counter() - start:.0f} s)", flush=True)


def _train_on_tokens(config_module, preset: str, run_cls, trainer, on_tokens, workdir) -> None:
  """Trains `trainer.train` on the dataset and tokeniser `on_tokens` = (data_dir, tokenizer_dir)
  into `workdir`, with `config_module`'s `preset` (as `run_cls`) and the demo's seed."""
  config = config_module.get_config(preset)
  config.data_dir, config.tokenizer_dir = (str(d) for d in on_tokens)
  config.seed = _SEED.value
  trainer.train(run_cls.from_config(config), workdir)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  root = Path(_WORKDIR.value)
  data_dir, tok_dir, diff_dir = root / "data", root / "tokenizer", root / "diffusion"
  base_dir, mdn_dir = root / "baseline", root / "mdn"
  start = time.perf_counter()

  _stage(f"1/5 dataset (SUMO, preset {_DATA.value}) -> {data_dir}", start)
  splits = dataset_lib.build(dataset_config.get_config(_DATA.value), data_dir)
  print({name: len(s) for name, s in splits.items()})

  _stage(f"2/5 CVQ-VAE tokeniser (preset {_TOKENIZER.value}) -> {tok_dir}", start)
  tok_cfg = tokenizer_config.get_config(_TOKENIZER.value)
  tok_cfg.data_dir, tok_cfg.seed = str(data_dir), _SEED.value
  tokenizer_train.train(TokenizerRunConfig.from_config(tok_cfg), tok_dir)

  _stage(f"3/5 motion diffusion (preset {_DIFFUSION.value}) -> {diff_dir}", start)
  on_tokens = (data_dir, tok_dir)
  _train_on_tokens(
      diffusion_config, _DIFFUSION.value, DiffusionRunConfig, diffusion_train, on_tokens, diff_dir
  )

  teacher = diff_dir
  for i, steps in enumerate(_DISTILL_STEPS.value):
    student = root / f"student_progressive_{steps}"
    kind = "progressive" if i else "guided progressive"
    # a halving: the student regresses two steps of its teacher (`:halving`)
    preset = f"{_DISTILL.value},halving" if i else _DISTILL.value
    _stage(f"3b/5 {kind} distillation, {steps} steps (preset {preset}) -> {student}", start)
    dist_cfg = distill_config.get_config(preset)
    dist_cfg.teacher_dir, dist_cfg.steps = str(teacher), int(steps)
    dist_cfg.guided_progressive, dist_cfg.seed = i == 0, _SEED.value
    distill_train.train(DistillRunConfig.from_config(dist_cfg), student)
    teacher = student

  _stage(f"4/5 multiple-choice MLP baseline (preset {_BASELINE.value}) -> {base_dir}", start)
  _train_on_tokens(
      baseline_config, _BASELINE.value, BaselineRunConfig, baseline_train, on_tokens, base_dir
  )

  _stage(f"4b/5 mixture density baseline (preset {_MDN.value}) -> {mdn_dir}", start)
  _train_on_tokens(mdn_config, _MDN.value, MDNRunConfig, mdn_train, on_tokens, mdn_dir)

  _stage(f"5/5 evaluation on the test and test_ood splits -> {root}", start)
  files = []
  for split in report.run_test_and_ood(
      tokenizer_dir=tok_dir,
      diffusion_dir=teacher,
      data_dir=data_dir,
      workdir=root,
      ddpm_scenarios=_DDPM.value,
      ood_ddpm_scenarios=_OOD_DDPM.value,
      baseline_dir=base_dir,
      mdn_dir=mdn_dir,
      ddpm_diffusion_dir=diff_dir,
  ):
    suffix = report.split_suffix(split)
    files += [f"{root}/metrics{suffix}.json", f"{root}/results{suffix}.md"]
    print(f"\n{split}:\n" + (root / f"results{suffix}.md").read_text())
  data_cfg = dataset_config.get_config(_DATA.value)
  held_out = sumo_plan.split_ids(data_cfg.sumo)["test_ood"] if data_cfg.source == "sumo" else []
  if held_out:  # the scene, moving: 3 s of the held-out road with every vehicle's hypotheses
    clip = root / "scene_test_ood.gif"
    animation.write_clip(
        Predictor.load(tok_dir, teacher), data_dir / "recordings", held_out[0], clip
    )
    files.append(str(clip))
  print(
      f"done in {time.perf_counter() - start:.0f} s, {memory.rss_line()}; reports: "
      f"{', '.join(files)}, {root}/*.png",
      flush=True,
  )


if __name__ == "__main__":
  cli.run(main, allocator=True)
