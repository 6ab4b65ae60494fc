"""NaN weights are refused where they are read (issue 48's probe): a distillation whose
teacher holds NaN stops before it writes anything, and a run whose latest checkpoint holds
NaN is not resumed (before: a traceback after config.json was written; exit 0)."""

import json

import jax
import jax.numpy as jnp
import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax import sharding
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import layout
from cvmdx_jax.storage import checkpointing
from cvmdx_jax.train import distill
from tests.train import toy


def _with_nan(tree):
  """`tree` with its first leaf's first entry NaN."""
  leaves, treedef = jax.tree.flatten(tree)
  leaves[0] = jnp.asarray(leaves[0]).ravel().at[0].set(jnp.nan).reshape(leaves[0].shape)
  return jax.tree.unflatten(treedef, leaves)


def test_a_teacher_holding_nan_is_refused_before_the_student_writes(tmp_path):
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("tiny")).with_tokens(4)
  params = _with_nan(unet1d.init_unet(config.model, jax.random.key(0))[1])
  teacher = tmp_path / "teacher"
  state = {"params": params, "ema_params": params, "step": jnp.zeros((), jnp.int32)}
  with checkpointing.Checkpoints(teacher / layout.CHECKPOINTS, keep=1) as ckpts:
    ckpts.save(1, state, {"fingerprint": {}})
  layout.write_run_config(teacher, config)
  student = tmp_path / "student"
  with pytest.raises(checkpointing.CheckpointMismatchError, match=r"/1 holds NaN in "):
    distill.train(DistillRunConfig(teacher_dir=str(teacher)), student)
  assert not student.exists()


def test_a_run_whose_latest_checkpoint_holds_nan_is_not_resumed(tmp_path):
  init_fn, step_fn = toy.make_task()
  run = dict(init_fn=init_fn, step_fn=step_fn, data=toy.make_data(), batch_size=8, seed=0)
  toy.train(workdir=tmp_path, num_epochs=1, fingerprint={"task": "toy"}, **run)
  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep),
      jax.eval_shape(init_fn, jax.random.key(0)),
  )
  with checkpointing.Checkpoints(tmp_path / layout.CHECKPOINTS) as ckpts:
    state, meta = ckpts.load(1, abstract)
    ckpts.save(2, {**state, "params": _with_nan(state["params"])}, meta)  # diverged
  with pytest.raises(checkpointing.CheckpointMismatchError, match=r"/2 holds NaN in 'params"):
    toy.train(workdir=tmp_path, num_epochs=3, fingerprint={"task": "toy"}, **run)
  lines = (tmp_path / "metrics.jsonl").read_text().splitlines()
  assert [json.loads(line)["epoch"] for line in lines] == [1]  # nothing trained on it
