"""A tiny NNX MLP regression task trained with AdamW, to exercise the shared loop."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx


class MLP(nnx.Module):
  """3 -> hidden -> 1 tanh MLP."""

  def __init__(self, hidden: int, rngs: nnx.Rngs):
    self.l1 = nnx.Linear(3, hidden, rngs=rngs)
    self.l2 = nnx.Linear(hidden, 1, rngs=rngs)

  def __call__(self, x: jax.Array) -> jax.Array:
    return self.l2(jnp.tanh(self.l1(x)))


def make_data(m: int = 40, seed: int = 0) -> dict[str, np.ndarray]:
  """x (m, 3) standard normal, y (m, 1) a smooth function of x."""
  rng = np.random.default_rng(seed)
  x = rng.normal(size=(m, 3)).astype(np.float32)
  y = (np.sin(x) @ np.array([1.0, -2.0, 0.5], np.float32))[:, None]
  return {"x": x, "y": y.astype(np.float32)}


def make_task(hidden: int = 8, lr: float = 1e-2, nan_at: int | None = None):
  """(init_fn, step_fn) for the loop; the loss is NaN at global step `nan_at` if given."""
  graphdef = nnx.split(nnx.eval_shape(lambda: MLP(hidden, nnx.Rngs(0))))[0]
  tx = optax.adamw(lr, weight_decay=1e-4)

  def init_fn(key):
    params = nnx.state(MLP(hidden, nnx.Rngs(key)), nnx.Param)
    return {"params": params, "opt": tx.init(params), "step": jnp.zeros((), jnp.int32)}

  def loss_fn(params, batch, key):
    pred = nnx.merge(graphdef, params)(batch["x"])
    target = batch["y"] + 0.01 * jax.random.normal(key, batch["y"].shape)
    err = jnp.sum((pred - target) ** 2, axis=-1)
    return jnp.sum(batch["weight"] * err) / jnp.sum(batch["weight"])

  def step_fn(state, batch, key):
    loss, grads = jax.value_and_grad(loss_fn)(state["params"], batch, key)
    if nan_at is not None:
      loss = jnp.where(state["step"] == nan_at, jnp.nan, loss)
    updates, opt = tx.update(grads, state["opt"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    new = {"params": params, "opt": opt, "step": state["step"] + 1}
    return new, {"loss": loss, "grad_norm": optax.tree.norm(grads)}

  return init_fn, step_fn


def flat_params(state) -> np.ndarray:
  """All parameters of a toy state as one float64 vector (host)."""
  return np.concatenate(
      [np.ravel(np.asarray(x, np.float64)) for x in jax.tree.leaves(state["params"])]
  )


def train(**kwargs):
  """`loop.train(**kwargs)` inside the workdir's lock, as the trainers call it."""
  from cvmdx_jax.storage import locking
  from cvmdx_jax.train import loop

  with locking.hold(kwargs["workdir"]):
    return loop.train(**kwargs)


def restore(workdir, init_fn, fingerprint=None):
  """(state, fingerprint) of the latest checkpoint of a `loop.train` run, restored into
  `init_fn`'s structure (replicated); CheckpointMismatchError when `fingerprint` is given
  and differs from the saved one."""
  from pathlib import Path

  from cvmdx_jax import sharding
  from cvmdx_jax.storage import checkpointing, identity

  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep),
      jax.eval_shape(init_fn, jax.random.key(0)),
  )
  root = Path(workdir) / "checkpoints"
  state, saved = checkpointing.load_latest(root, abstract)
  if fingerprint is not None:
    identity.check(
        saved["fingerprint"],
        fingerprint,
        f"checkpoint {root}",
        checkpointing.CheckpointMismatchError,
    )
  return state, saved["fingerprint"]
