"""Saved tokeniser outputs: tokens q, latents z_hat and delta per split, and the Gaussians.

Layout (decision: the outputs live in the tokeniser's work directory, and "next to the
dataset" is met by recording the dataset id and path in the metadata, so one dataset
can be tokenised by several tokenisers without them overwriting each other):

    <workdir>/tokens/<split>.npz     q (M,) int32, z_hat (M, D) float32, delta (M,) float32
    <workdir>/tokens/gaussians.npz   mean (Q, D), cov (Q, D, D), precision (Q, D, D), count (Q,)

Each file holds a JSON `metadata` string: dataset_id, data_dir, split, num_scenarios,
codebook_size, latent_dim, quantizer and the tokeniser checkpoint (workdir, step,
fingerprint, params_id). Files are written atomically and checksummed
(`storage.checksums`): a reader never sees a half-written one, and a corrupted one raises
`checksums.CorruptRunError` naming it. `load_tokens(..., dataset_id=...)` refuses tokens
made from another dataset with `TokensMismatchError` (`storage.identity.check`).
"""

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from cvmdx_jax.errors import UserError
from cvmdx_jax.models.uncertainty import Gaussians
from cvmdx_jax.storage import checksums, identity

GAUSSIANS_NAME = "gaussians"


class TokensMismatchError(UserError):
  """Saved tokens do not belong to the dataset or tokeniser they are loaded for."""


@dataclasses.dataclass(frozen=True)
class Tokens:
  """Tokeniser outputs for M scenarios (numpy).

  Attributes:
    q: (M,) int32 token.
    z_hat: (M, D) float32 encoder latent.
    delta: (M,) float32 Mahalanobis distance to the token's Gaussian.
  """

  q: np.ndarray
  z_hat: np.ndarray
  delta: np.ndarray


def tokens_path(workdir: str | os.PathLike, split: str) -> Path:
  """<workdir>/tokens/<split>.npz."""
  return Path(workdir) / "tokens" / f"{split}.npz"


def gaussians_path(workdir: str | os.PathLike) -> Path:
  """<workdir>/tokens/gaussians.npz."""
  return Path(workdir) / "tokens" / f"{GAUSSIANS_NAME}.npz"


def _write_npz(path: Path, arrays: dict, metadata: dict) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  checksums.write_npz(path, metadata=np.array(json.dumps(metadata, sort_keys=True)), **arrays)


def _read_npz(path: Path, names: tuple[str, ...]) -> tuple[dict, dict]:
  if not path.is_file():
    raise FileNotFoundError(f"{path}: no such tokens file (train the tokeniser first)")
  data = checksums.read_npz(path)
  missing = [n for n in (*names, "metadata") if n not in data]
  arrays = {n: data[n] for n in names if n in data}
  try:
    metadata = json.loads(str(data["metadata"])) if "metadata" in data else {}
  except ValueError as e:
    raise checksums.CorruptRunError(f"{path}: unreadable metadata ({e})") from e
  if missing:
    raise UserError(f"{path}: missing field(s) {missing}")
  return arrays, metadata


def save_tokens(path: str | os.PathLike, tokens: Tokens, metadata: dict) -> None:
  """Writes tokens + metadata (JSON-able dict) atomically to `path` (.npz)."""
  m = tokens.q.shape[0]
  if tokens.z_hat.shape[0] != m or tokens.delta.shape != (m,):
    raise UserError(
        f"{path}: q {tokens.q.shape}, z_hat {tokens.z_hat.shape} and delta "
        f"{tokens.delta.shape} disagree on the number of scenarios"
    )
  arrays = {
      "q": np.asarray(tokens.q, np.int32),
      "z_hat": np.asarray(tokens.z_hat, np.float32),
      "delta": np.asarray(tokens.delta, np.float32),
  }
  _write_npz(Path(path), arrays, {**metadata, "num_scenarios": int(m)})


def load_tokens(
    path: str | os.PathLike, *, dataset_id: str | None = None, num_scenarios: int | None = None
) -> tuple[Tokens, dict]:
  """Reads tokens saved by `save_tokens`.

  Args:
    path: the .npz file.
    dataset_id: if given, the id of the dataset the tokens must come from.
    num_scenarios: if given, the number of scenarios of the split they must cover.

  Returns:
    (Tokens, metadata).

  Raises:
    TokensMismatchError: the tokens come from another dataset or have another length.
  """
  path = Path(path)
  arrays, metadata = _read_npz(path, ("q", "z_hat", "delta"))
  if dataset_id is not None:
    identity.check(
        {"dataset_id": metadata.get("dataset_id")},
        {"dataset_id": dataset_id},
        f"{path} (tokens of data_dir {metadata.get('data_dir')!r}; re-run the "
        "tokeniser on this dataset)",
        TokensMismatchError,
    )
  if num_scenarios is not None and arrays["q"].shape[0] != num_scenarios:
    raise TokensMismatchError(
        f"{path}: tokens cover {arrays['q'].shape[0]} scenarios, " f"the split has {num_scenarios}"
    )
  return Tokens(**arrays), metadata


def save_gaussians(path: str | os.PathLike, gaussians: Gaussians, metadata: dict) -> None:
  """Writes the per-entry Gaussians + metadata atomically to `path` (.npz)."""
  arrays = {
      f.name: np.asarray(getattr(gaussians, f.name), np.float32)
      for f in dataclasses.fields(Gaussians)
  }
  _write_npz(Path(path), arrays, metadata)


def load_gaussians(path: str | os.PathLike) -> tuple[Gaussians, dict]:
  """Reads Gaussians saved by `save_gaussians` -> (Gaussians of numpy arrays, metadata)."""
  names = tuple(f.name for f in dataclasses.fields(Gaussians))
  arrays, metadata = _read_npz(Path(path), names)
  return Gaussians(**arrays), metadata
