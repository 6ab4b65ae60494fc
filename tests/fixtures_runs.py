"""Tiny trained runs shared by the pipeline and integrity tests (fixture `tiny_runs` of
tests/conftest.py): a SUMO dataset `:tiny`, a tokeniser `:tiny` and a denoiser `:tiny` on its
tokens, built once per test session. Tests read them and write elsewhere (`tmp_path`)."""

import fcntl
from pathlib import Path

from configs import dataset as dataset_config
from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.runs import DiffusionRunConfig, TokenizerRunConfig
from cvmdx_jax.data import dataset
from cvmdx_jax.train import diffusion, tokenizer

DONE = ".built"  # written last: the runs under a root with it are whole


def tokenizer_config_for(data_dir, arg: str = "tiny"):
  """configs/tokenizer.py:`arg` reading `data_dir`."""
  config = tokenizer_config.get_config(arg)
  config.data_dir = str(data_dir)
  return config


def diffusion_config_for(data_dir, tokenizer_dir):
  """configs/diffusion.py:tiny on the dataset `data_dir` and the tokens of `tokenizer_dir`."""
  config = diffusion_config.get_config("tiny")
  config.data_dir, config.tokenizer_dir = str(data_dir), str(tokenizer_dir)
  return config


def train_tokenizer(config, workdir, **kwargs):
  """Trains a tokeniser from a ConfigDict (typed as the entry point types it)."""
  return tokenizer.train(TokenizerRunConfig.from_config(config), workdir, **kwargs)


def train_diffusion(config, workdir):
  """Trains a denoiser from a ConfigDict (typed as the entry point types it)."""
  return diffusion.train(DiffusionRunConfig.from_config(config), workdir)


def build(root: Path) -> Path:
  """root/data, root/tokenizer, root/diffusion, built once: several processes (xdist
  workers) may call it with one root; the first builds while the others wait."""
  root.mkdir(parents=True, exist_ok=True)
  with open(root / ".lock", "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    if not (root / DONE).exists():
      dataset.build(dataset_config.get_config("tiny"), root / "data")
      train_tokenizer(tokenizer_config_for(root / "data"), root / "tokenizer")
      train_diffusion(diffusion_config_for(root / "data", root / "tokenizer"), root / "diffusion")
      (root / DONE).touch()
  return root
