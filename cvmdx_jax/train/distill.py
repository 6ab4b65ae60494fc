"""Distillation of a trained denoiser into a few-step student, on the shared loop.

One run is one stage (`diffusion.distillation`), chosen by the teacher:
- a guided denoiser (a diffusion run) teaches a *guidance student*: the same U-Net with
  the guidance weight w as one more FiLM feature, initialised from the teacher with a
  zero weight row for w (a token-only teacher gets a new FiLM MLP whose output layer is
  zero), so that before training it returns the teacher's conditional v;
- a guidance student teaches a *progressive student* for `steps` steps, sampled by the
  teacher at k `steps` (k = `teacher_substeps`, 2 by default: a progressive teacher must
  have been distilled for k `steps`);
- with `guided_progressive`, a guided denoiser teaches a progressive student directly
  (stage "guided_progressive"): the targets are k DDIM steps of the guided pair on the
  grid of k `steps`, the student initialised as for the guidance stage. One run instead
  of two, each step 2 k teacher evaluations (docs/log, "One distillation stage").

x_t is the training data noised by the forward process (t uniform over the T steps for
the guidance stage, over the student's grid for the progressive ones), w = w(t, delta)
with the teacher's guidance settings and each scenario's token uncertainty, the loss the
weighted mean squared v error (the teacher's class weights). The run directory is a
diffusion run directory (config.json = the student's `DiffusionRunConfig`, sampler
"distilled"; checkpoints with the EMA parameters), so `Predictor.load` and
`evaluate.py --diffusion_dir` take it as they are; its fingerprint adds the teacher's
fingerprint and the content id of its parameters, so a resume with another teacher is
refused.
"""

import dataclasses
import os

import jax
import jax.numpy as jnp
import optax
from flax import traverse_util

from cvmdx_jax import ego_motion
from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig
from cvmdx_jax.diffusion import cosine_schedule, distillation, guidance_weight, guided_v_fn, param
from cvmdx_jax.diffusion.losses import weighted_mse
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference.bundles import Denoiser, load_denoiser
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import fingerprints, layout, loaders
from cvmdx_jax.storage import identity, locking
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import loop


class TeacherMismatchError(UserError):
  """The teacher cannot teach this run (wrong kind, steps or data)."""


def stage_of(teacher: DiffusionRunConfig, guided_progressive: bool = False) -> str:
  """ "progressive" for a student teacher; for a guided denoiser "guided_progressive" if
  asked, else "guidance"."""
  if teacher.diffusion.guidance_input:
    return "progressive"
  return "guided_progressive" if guided_progressive else "guidance"


def student_config(teacher: DiffusionRunConfig, config: DistillRunConfig) -> DiffusionRunConfig:
  """The student's run config: the teacher's with w as an input (guidance stage), the
  distillation's seed and optimiser, and the distilled sampler at `config.steps` (an
  intent classifier is the teacher's, copied)."""
  diffusion = dataclasses.replace(teacher.diffusion, guidance_input=True)
  sampling = dataclasses.replace(
      teacher.sampling, sampler="distilled", steps=config.steps, mode="paper"
  )
  return dataclasses.replace(
      teacher,
      data_dir=config.data_dir or teacher.data_dir,
      tokenizer_dir=config.tokenizer_dir or teacher.tokenizer_dir,
      seed=config.seed,
      model=dataclasses.replace(teacher.model, cond_dim=diffusion.cond_dim),
      diffusion=diffusion,
      train=config.train,
      sampling=sampling,
  )


def student_params(teacher_params: dict, fresh: dict) -> dict:
  """The student's initial parameters: `fresh` (the student's own init) with every
  teacher leaf of the same path and shape; the teacher's first FiLM layer gets a zero
  row for w; a FiLM MLP the teacher lacks keeps its fresh hidden layers and a zero output
  layer (so the student's output equals the teacher's conditional v)."""
  teacher = traverse_util.flatten_dict(teacher_params)
  out = {}
  for path, leaf in traverse_util.flatten_dict(fresh).items():
    old = teacher.get(path)
    if old is not None and old.shape == leaf.shape:
      out[path] = old
    elif old is not None and path[-1] == "kernel" and old.shape[1:] == leaf.shape[1:]:
      out[path] = jnp.concatenate(
          [old, jnp.zeros((leaf.shape[0] - old.shape[0],) + leaf.shape[1:], leaf.dtype)]
      )
    elif old is None and path[0] == "cond_mlp2":
      out[path] = jnp.zeros_like(leaf)
    elif old is None and path[0] in ("cond_mlp1", "cond_mlp_hidden"):
      out[path] = leaf
    else:
      raise TeacherMismatchError(
          f"student parameter {'/'.join(map(str, path))} "
          f"{leaf.shape} has no teacher counterpart "
          f"({None if old is None else old.shape})"
      )
  return traverse_util.unflatten_dict(out)


def make_init_fn(teacher_params: dict, cfg: UNetConfig, tx, start_params: dict | None = None):
  """init_fn(key) -> {params, ema_params, opt_state, step, teacher}; the student starts
  from `start_params` (a student's, `init_dir`) or from the teacher's."""

  def init_fn(key):
    _, fresh = unet1d.init_unet(cfg, key)
    params = student_params(teacher_params if start_params is None else start_params, fresh)
    return {
        "params": params,
        "ema_params": jax.tree.map(jnp.copy, params),
        "opt_state": tx.init(params),
        "step": jnp.zeros((), jnp.int32),
        "teacher": jax.tree.map(jnp.copy, teacher_params),
    }

  return init_fn


def make_step_fn(teacher: Denoiser, student: DiffusionRunConfig, tx, *, stage: str, substeps: int):
  """The pure train step: the teacher's v-target at noised data (for a progressive stage
  `substeps` teacher steps per student step), the student's v-loss, AdamW and the EMA
  (`train.diffusion.apply_gradients`)."""
  d = student.diffusion
  schedule = cosine_schedule(d.num_steps)
  guidance, steps, clip = (
      student.sampling.guidance,
      student.sampling.steps,
      student.sampling.clip_x0,
  )
  graphdef = unet1d.make_graphdef(student.model)
  film = ego_motion.uses_film(d.conditioning)

  def step_fn(state, batch, key):
    k_t, k_eps = jax.random.split(key)
    x0, q, delta = batch["x0"], batch["q"], batch["delta"]
    ego = batch["ego"] if film else None
    eps = jax.random.normal(k_eps, x0.shape, x0.dtype)
    w_of = lambda t: guidance_weight(t, delta, d.num_steps, guidance)
    if stage == "progressive":  # the teacher is a student: w is its input
      teacher_v = lambda x, tt: unet1d.apply_unet(
          teacher.graphdef,
          state["teacher"],
          x,
          tt,
          q,
          cond=distillation.student_cond(ego, w_of(tt)),
      )
    else:  # the guided pair runs both branches in one call of 2B rows
      pair = lambda x: None if ego is None else jnp.tile(ego, (x.shape[0] // ego.shape[0], 1))
      model = lambda x, tt, c: unet1d.apply_unet(
          teacher.graphdef, state["teacher"], x, tt, c, cond=pair(x)
      )
      teacher_v = guided_v_fn(model, q, teacher.null_token, delta, schedule, guidance)
    if stage == "guidance":
      t = jax.random.randint(k_t, (x0.shape[0],), 0, d.num_steps)
      x_t = param.q_sample(x0, eps, schedule.alphas_cumprod[t])
      target = teacher_v(x_t, t)
    else:
      index = jax.random.randint(k_t, (x0.shape[0],), 0, steps)
      ts, abars, abar_next = distillation.progressive_grid(schedule, steps, index, substeps)
      t = ts[:, 0]
      x_t = param.q_sample(x0, eps, abars[:, 0])
      target = distillation.progressive_target(teacher_v, x_t, ts, abars, abar_next, clip)
    target = jax.lax.stop_gradient(target)
    cond = distillation.student_cond(ego, w_of(t))
    weight = batch["weight"] * batch.get("class_weight", 1.0)

    def loss_fn(params):
      return weighted_mse(unet1d.apply_unet(graphdef, params, x_t, t, q, cond=cond), target, weight)

    loss, grads = jax.value_and_grad(loss_fn)(state["params"])
    return (
        diffusion_train.apply_gradients(state, grads, tx, student.train.ema_decay),
        {"loss": loss, "grad_norm": optax.tree.norm(grads)},
    )

  return step_fn


def check_teacher(teacher: Denoiser, config: DistillRunConfig) -> str:
  """The stage the teacher teaches; TeacherMismatchError where it cannot teach this run."""
  stage = stage_of(teacher.config, config.guided_progressive)
  if config.guided_progressive and stage != "guided_progressive":
    raise TeacherMismatchError(
        f"guided_progressive: teacher {config.teacher_dir} is a distilled student, not a "
        "guided denoiser (a student teaches progressive students without it)"
    )
  k = config.teacher_substeps
  if teacher.progressive and teacher.config.sampling.steps != k * config.steps:
    raise TeacherMismatchError(
        f"teacher {config.teacher_dir} is a progressive student for "
        f"{teacher.config.sampling.steps} steps: with teacher_substeps={k} it teaches a "
        f"student for {teacher.config.sampling.steps / k:g} steps, not steps={config.steps}"
    )
  if k * config.steps >= teacher.config.diffusion.num_steps:
    raise TeacherMismatchError(
        f"steps={config.steps}: the teacher's grid of teacher_substeps x steps = "
        f"{k * config.steps} must stay below T = {teacher.config.diffusion.num_steps}"
    )
  return stage


def load_start(config: DistillRunConfig, student: DiffusionRunConfig) -> dict | None:
  """The parameters of the run `config.init_dir` that start the student (None for ""); a
  TeacherMismatchError where its U-Net is not the student's."""
  if not config.init_dir:
    return None
  start_config, start_params, _ = loaders.read_denoiser(config.init_dir)  # no graph needed
  if start_config.model != student.model:
    raise TeacherMismatchError(
        f"init_dir: {config.init_dir} is not a distilled run of this student's U-Net "
        "(its model section differs; a student of the same teacher starts another)"
    )
  return start_params


@locking.holds("workdir")
def train(config: DistillRunConfig, workdir: str | os.PathLike):
  """Distils the teacher run `config.teacher_dir` into `workdir` (resuming if possible);
  returns the final state.

  Raises:
    TeacherMismatchError: the teacher cannot teach this run (a progressive student of
      other steps) or its fingerprint does not name the data / tokens at hand.
    CheckpointMismatchError: the workdir's checkpoint belongs to another run (e.g.
      another teacher: the message names `distill.teacher.params_id`).
  """
  teacher = load_denoiser(config.teacher_dir)
  stage = check_teacher(teacher, config)
  student = student_config(teacher.config, config)
  start = load_start(config, student)
  data, num_tokens, dataset_id, tokens_meta = diffusion_train.training_data(student, delta=True)
  fingerprint = fingerprints.diffusion(student, dataset_id, tokens_meta)
  saved = teacher.fingerprint.to_dict()
  identity.check(
      {k: saved.get(k) for k in ("dataset_id", "tokenizer")},
      {k: fingerprint[k] for k in ("dataset_id", "tokenizer")},
      f"teacher {config.teacher_dir} (trained on other data or tokens than "
      f"{student.data_dir} / {student.tokenizer_dir})",
      TeacherMismatchError,
  )
  if num_tokens != teacher.config.model.num_tokens:
    raise TeacherMismatchError(
        f"teacher {config.teacher_dir} has "
        f"{teacher.config.model.num_tokens} tokens, the tokens have "
        f"{num_tokens}"
    )
  train_cfg = {
      k: v
      for k, v in dataclasses.asdict(config.train).items()
      if k not in ("checkpoint_every", "keep")
  }
  fingerprint["distill"] = {
      "stage": stage,
      "steps": config.steps,
      "teacher_substeps": config.teacher_substeps,
      "train": train_cfg,
      "guidance": dataclasses.asdict(student.sampling.guidance),
      "clip_x0": student.sampling.clip_x0,
      "teacher": {"fingerprint": saved, "params_id": identity.content_id(teacher.params)},
  }
  if start is not None:
    fingerprint["distill"]["init"] = identity.content_id(start)
  total_steps = (
      loop.steps_per_epoch(len(data["q"]), config.train.batch_size) * config.train.num_epochs
  )
  tx = diffusion_train.optimizer(config.train, total_steps)
  return loop.train(
      workdir=workdir,
      init_fn=make_init_fn(teacher.params, student.model, tx, start),
      step_fn=make_step_fn(teacher, student, tx, stage=stage, substeps=config.teacher_substeps),
      data=data,
      fingerprint=fingerprint,
      **loop.run_settings(config),
      on_start=lambda: layout.write_run_config(workdir, student),
      desc=f"distill ({stage})",
  )
