"""Distillation config (`cvmdx_jax.train.distill`, beyond the paper): one stage from a teacher.

Run (after train_diffusion), the `make demo` students (a 2-step one, then its halving):
  .venv/bin/python experiments/distill.py --config=configs/distill.py:demo \\
      --config.teacher_dir=runs/demo/diffusion --config.steps=2 \\
      --config.guided_progressive=True --workdir=runs/demo/student_progressive_2
  .venv/bin/python experiments/distill.py --config=configs/distill.py:demo,halving \\
      --config.teacher_dir=runs/demo/student_progressive_2 --config.steps=1 \\
      --workdir=runs/demo/student_progressive_1
or a guidance student, then a progressive one:
  .venv/bin/python experiments/distill.py --config=configs/distill.py:demo \\
      --config.teacher_dir=runs/demo/diffusion --workdir=runs/demo/distill_guidance
  .venv/bin/python experiments/distill.py --config=configs/distill.py:demo \\
      --config.teacher_dir=runs/demo/distill_guidance --config.steps=2 \\
      --workdir=runs/demo/distill
A guided denoiser teaches a guidance student (w as an input, one U-Net evaluation per
step) or, with `guided_progressive`, a progressive student for `steps` steps directly; a
student teaches a progressive student for `steps` steps. Each progressive student step
regresses `teacher_substeps` (k) DDIM steps of its teacher: `:demo` takes k = 5 (the
guided teacher's 10-step DDIM for a 2-step student); a progressive teacher samples only
its own steps, so halving one needs k = 2 (`--config.teacher_substeps=2`). Presets after
the path: `:tiny` (seconds, tests), `:demo` (the `make demo` stage on 2 cores), `halving`
beside either (k = 2; `:demo,halving`: the demo's 1-step stage), `long` beside `:demo` (8
epochs for the guided-progressive stage and 15 for its halving: `run_demo.py
--distill_preset=demo,long` trains both, ~10 min on 2 cores against the demo's 4-5).
`init_dir` starts the student from another student's parameters (same U-Net) instead of
the teacher's. Any field can be overridden: `--config.train.num_epochs=20`; the entry
point checks every field once (`cvmdx_jax.config.runs.DistillRunConfig`).
"""

import ml_collections

from configs import common
from cvmdx_jax.errors import UserError

# The default pipeline's students (`make demo`, experiments/run_demo.py --distill_steps): a
# progressive student for 2 steps taught by the guided denoiser's 10-step DDIM in one stage
# (`:demo`'s teacher_substeps), then its halving to 1 step (`:demo,halving`, 10 epochs):
# one U-Net evaluation a sample, within 3 % of guided DDIM-10 in mean ADE, minFDE_K and
# energy score on the large val and val_ood sets
# (docs/log/2026-12-06-one-step-large-val.md); `--distill_steps=2` stops at the 2-step
# student. experiments/benchmark.py times the last one.
STUDENTS = (2, 1)


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  """Returns the distillation config for `arg` (see the module docstring)."""
  arg = common.parse_arg(arg, tiny=False, demo=False, halving=False, long=False)
  if arg.long and not arg.demo:
    raise UserError("configs/distill.py: 'long' extends ':demo' (demo,long)")
  config = ml_collections.ConfigDict()
  config.teacher_dir = "runs/diffusion"  # the teacher run (diffusion or distillation)
  config.data_dir = ""  # "" = the teacher's (its config.json)
  config.tokenizer_dir = ""  # "" = the teacher's
  config.seed = 0  # noise, timesteps, example order, the new FiLM layer
  config.steps = 4  # S: the student's sampling steps (sampler "distilled")
  # a guided denoiser teaches a progressive student for `steps` directly (its targets: k
  # DDIM steps of the guided pair on the grid of k S) instead of a guidance student
  config.guided_progressive = False
  # k: the teacher's DDIM steps per student step of a progressive stage (2: a halving)
  config.teacher_substeps = 2
  # a distilled run of the same U-Net whose parameters start the student ("" = the teacher)
  config.init_dir = ""

  config.train = ml_collections.ConfigDict()
  config.train.batch_size = 256  # global batch
  config.train.num_epochs = 20  # epochs over the teacher's train split
  config.train.learning_rate = 1e-4  # peak AdamW lr
  config.train.warmup_steps = 100  # linear warm-up; capped at 10 % of the run
  config.train.min_lr = 1e-6  # end of the cosine decay
  config.train.weight_decay = 0.0  # AdamW decoupled weight decay
  config.train.grad_clip = 1.0  # global-norm clipping
  config.train.ema_decay = 0.999  # EMA of the weights used for inference
  config.train.checkpoint_every = 5  # epochs between checkpoints
  config.train.keep = 2  # checkpoints kept

  if arg.tiny:
    config.train.batch_size = 16
    config.train.num_epochs = 1
    config.train.learning_rate = 1e-3
    config.train.checkpoint_every = 1
  if arg.demo:
    # ~120 steps over the :small train split, ~1.5 min on 2 cores: `make demo`'s one
    # guided-progressive stage. It regresses the guided teacher's 10-step DDIM (5 teacher
    # steps a student step) instead of its 4-step one: on val (64 samples, k-means K = 3)
    # mean ADE 0.729, minFDE_K 1.250, Brier-minFDE 1.599 against DDIM-10's 0.732 / 1.255 /
    # 1.591 (k = 2 and 4 epochs, the demo until 2026-12-02: 0.734 / 1.281 / 1.668); 3
    # epochs match 4 (0.727 / 1.252 / 1.603) at ~1.3x the epoch time of k = 2
    # (docs/log, "A 10-step teacher for the 2-step student"); 2 epochs are within 1 % of 3
    # on val and val_ood (mean ADE, minFDE_K, energy score) and keep `make demo` within
    # 15 min (docs/log/2026-12-06-demo-time.md)
    config.train.batch_size = 128
    config.train.num_epochs = 2
    config.train.learning_rate = 3e-4
    config.train.checkpoint_every = 2  # a save costs ~2.5 s on 2 cores
    config.teacher_substeps = 5
  if arg.long and not arg.halving:
    # a longer 2-step teacher for the 1-step student: 8 epochs; its 15-epoch halving
    # (`demo,long,halving`) is within 3 % of DDIM-10 on the large val sets, as the demo's
    # 10-epoch halving of the 2-epoch student is, at ~2.5x the distillation time
    # (docs/log/2026-12-06-one-step-large-val.md)
    config.train.num_epochs = 8
  if arg.halving:
    # a progressive student halves its teacher's steps: 2 teacher steps a student step. The
    # demo's 1-step student: 10 epochs of the 2-epoch student's halving (on the large val
    # and val_ood sets 6 epochs miss the 3 % rule, 10 pass), 15 after `long`'s teacher
    # (docs/log/2026-12-06-one-step-large-val.md)
    config.teacher_substeps = 2
    if arg.demo:
      config.train.num_epochs = 15 if arg.long else 10
      config.train.checkpoint_every = 5
  return config
