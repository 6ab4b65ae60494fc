"""A synthetic three-mode dataset with saved tokens, for the baseline's training tests.

The ego drives straight at 20-30 m/s; its future ends 3.5 m right (label 1), 3.5 m left
(label 2) or in its lane (label 0) along a smoothstep. The observed window is the same
for every mode, so only the token tells the mode: q = label for two thirds of the
scenarios, a fourth token (no information) for the rest.
"""

import json
import shutil
from pathlib import Path

import jax
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.data import cache
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.data.scenarios import from_arrays
from cvmdx_jax.runs import tokens as tokens_lib

LANE_M = 3.5
NUM_TOKENS = 4
TOKENIZER_CHECKPOINT = {"fingerprint": {"kind": "synthetic"}, "step": 7, "params_id": "0" * 64}


def make_scenarios(m: int, seed: int):
  rng = np.random.default_rng(seed)
  label = np.arange(m) % constants.NUM_CLASSES
  v0 = rng.uniform(20.0, 30.0, m).astype(np.float32)
  t_obs = (np.arange(constants.T_OBS) - (constants.T_OBS - 1)) * constants.DT
  xi = np.zeros((m, constants.NUM_VEHICLES, constants.T_OBS, 4), np.float32)
  xi[:, 0, :, 0] = v0[:, None] * t_obs
  xi[:, 0, :, 2] = v0[:, None]
  mask = np.zeros((m, constants.NUM_VEHICLES, constants.T_OBS), bool)
  mask[:, 0] = True
  t = np.arange(1, constants.T_PRED + 1) * constants.DT
  s = t / t[-1]
  end_y = np.array([0.0, -LANE_M, LANE_M])[label]
  future = np.stack([v0[:, None] * t, end_y[:, None] * (3 * s**2 - 2 * s**3)], axis=-1)
  zeros = np.zeros((m, constants.T_PRED, 2), np.float32)
  return from_arrays(
      xi=xi, mask=mask, future=future, controls=zeros, v0=v0, psi0=np.zeros(m), label=label
  )


def write(data_dir: Path, tokenizer_dir: Path, sizes=(("train", 48), ("val", 24))) -> None:
  """Writes the dataset cache under `data_dir` and its tokens under `tokenizer_dir`."""
  splits = {name: make_scenarios(m, seed) for seed, (name, m) in enumerate(sizes)}
  cache.write(Path(data_dir) / "cache", splits, {"synthetic": True}, [])
  meta = {
      "dataset_id": dataset_lib.dataset_id(data_dir),
      "codebook_size": NUM_TOKENS,
      "checkpoint": TOKENIZER_CHECKPOINT,
  }
  for name, s in splits.items():
    rng = np.random.default_rng(len(s))
    q = np.where((np.arange(len(s)) // 3) % 3 < 2, s.label, NUM_TOKENS - 1).astype(np.int32)
    toks = tokens_lib.Tokens(
        q=q,
        z_hat=np.zeros((len(s), 2), np.float32),
        delta=rng.uniform(0, 5, len(s)).astype(np.float32),
    )
    tokens_lib.save_tokens(
        tokens_lib.tokens_path(tokenizer_dir, name), toks, {**meta, "split": name}
    )


def written(root: Path) -> Path:
  """`root` once `write` has put the dataset in `root/data` and its tokens in
  `root/tokenizer` (what `run_config` points a run at)."""
  write(root / "data", root / "tokenizer")
  return root


def run_config(config, root: Path, **train):
  """A learned baseline's :tiny preset `config` on `write`'s data and tokens under `root`:
  4 epochs at lr 3e-3, every epoch's checkpoint kept (for the resume test); `train`
  overrides fields of its train section."""
  config.data_dir, config.tokenizer_dir = str(root / "data"), str(root / "tokenizer")
  config.train.num_epochs = 4
  config.train.learning_rate = 3e-3
  config.train.keep = 4
  config.train.update(train)
  return config


def curve(workdir: Path) -> list[dict]:
  """The metrics lines of the run in `workdir`."""
  return [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]


def assert_resumes_bit_identically(trained: Path, workdir: Path, train_again, params) -> None:
  """A copy at `workdir` of the finished 4-epoch run `trained` without its epochs 3 and 4 (as
  if killed after epoch 2), finished by `train_again(workdir)`, ends with `trained`'s
  parameters (`params(run directory)`) and metrics lines (but the seconds), bit for bit."""
  shutil.copytree(trained, workdir)
  for epoch in (3, 4):
    shutil.rmtree(workdir / "checkpoints" / str(epoch))
  train_again(workdir)
  jax.tree.map(np.testing.assert_array_equal, params(workdir), params(trained))
  assert curve(workdir) == [
      {**r, "seconds": s["seconds"]} for r, s in zip(curve(trained), curve(workdir))
  ]


def assert_every_leaf_differs(params, other) -> None:
  """Every parameter array of `params` differs from `other`'s somewhere (another seed)."""
  differs = jax.tree.map(lambda a, b: bool(np.any(a != b)), params, other)
  assert all(jax.tree.leaves(differs))
