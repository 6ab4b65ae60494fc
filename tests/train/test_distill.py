"""The distillation student's start: the teacher's network with w as one more FiLM input."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cvmdx_jax.diffusion import distillation
from cvmdx_jax.models import unet1d
from cvmdx_jax.train import distill
from tests.models import tiny_nets

TINY = tiny_nets.unet_config(5)


@pytest.mark.parametrize("features,hidden", [(0, ()), (3, ()), (0, (16, 8)), (3, (16, 8))])
def test_the_student_starts_as_the_teachers_conditional_branch(features, hidden):
  teacher_cfg = dataclasses.replace(TINY, cond_dim=features, cond_hidden=hidden)
  student_cfg = dataclasses.replace(TINY, cond_dim=features + 1, cond_hidden=hidden)
  graphdef, teacher = unet1d.init_unet(teacher_cfg, jax.random.key(0))
  # a trained-looking teacher: its zero-initialised output layer would hide everything
  leaves, tree = jax.tree.flatten(teacher)
  keys = jax.random.split(jax.random.key(4), len(leaves))
  teacher = jax.tree.unflatten(
      tree, [p + 0.1 * jax.random.normal(k, p.shape) for p, k in zip(leaves, keys)]
  )
  student_graphdef, fresh = unet1d.init_unet(student_cfg, jax.random.key(1))
  student = distill.student_params(teacher, fresh)
  x = jax.random.normal(jax.random.key(2), (4, 125, 2))
  t, q = jnp.array([0, 10, 500, 999]), jnp.array([0, 1, 4, 5])
  ego = jax.random.normal(jax.random.key(3), (4, features)) if features else None
  want = unet1d.apply_unet(graphdef, teacher, x, t, q, cond=ego)
  assert float(jnp.abs(want).mean()) > 1e-2
  for w in (0.0, 0.37, 2.0):
    got = unet1d.apply_unet(
        student_graphdef, student, x, t, q, cond=distillation.student_cond(ego, jnp.full((4,), w))
    )
    np.testing.assert_allclose(got, want, atol=1e-6, rtol=1e-6)
  # and w can move it: the new inputs are trainable, not frozen zeros everywhere
  grads = jax.grad(
      lambda p: jnp.sum(
          unet1d.apply_unet(
              student_graphdef, p, x, t, q, cond=distillation.student_cond(ego, jnp.ones(4))
          )
      )
  )(student)
  assert float(jnp.abs(grads["cond_mlp2"]["kernel"]).sum()) > 0


def test_a_student_the_teacher_cannot_fill_is_refused():
  _, teacher = unet1d.init_unet(TINY, jax.random.key(0))
  _, fresh = unet1d.init_unet(dataclasses.replace(TINY, base_channels=32), jax.random.key(1))
  with pytest.raises(distill.TeacherMismatchError, match="no teacher counterpart"):
    distill.student_params(teacher, fresh)


def test_a_student_started_from_another_student_keeps_its_parameters():
  student_cfg = dataclasses.replace(TINY, cond_dim=1)
  _, start = unet1d.init_unet(student_cfg, jax.random.key(0))
  start = jax.tree.map(lambda p: p + 0.25, start)  # not the fresh init of any key
  _, teacher = unet1d.init_unet(TINY, jax.random.key(1))
  tx = optax.adam(1e-3)
  state = distill.make_init_fn(teacher, student_cfg, tx, start)(jax.random.key(2))
  jax.tree.map(np.testing.assert_array_equal, state["params"], start)
  jax.tree.map(np.testing.assert_array_equal, state["ema_params"], start)
  jax.tree.map(np.testing.assert_array_equal, state["teacher"], teacher)
