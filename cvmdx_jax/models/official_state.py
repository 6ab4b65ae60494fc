"""An official cVMDx checkpoint's state dict: recognised and unwrapped from what a `.pt`
file holds (`unwrap_state_dict`), and the U-Net it implies (`unet_config`: Q, widths,
levels, attention levels, read from the parameter names and shapes; the number of heads is
not stored, official default 4). `official_import` converts its weights."""

import numpy as np

from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.errors import UserError

OFFICIAL_NUM_HEADS = 4
OFFICIAL_GROUPS = 32  # the official GroupNorm32 always uses 32 groups
_CANDIDATE_KEYS = ("label_emb.weight", "time_embed.0.weight", "input_blocks.0.0.weight")


class OfficialCheckpointError(UserError):
  """A checkpoint that is not a state dict of the official cVMDx U-Net."""


class NumHeadsError(OfficialCheckpointError):
  """A number of attention heads that does not divide the attention blocks' channels."""


def _is_state_dict(obj) -> bool:
  return (
      isinstance(obj, dict)
      and bool(obj)
      and all(isinstance(v, np.ndarray) for v in obj.values())
      and any(isinstance(k, str) and k.removeprefix("module.") in _CANDIDATE_KEYS for k in obj)
  )


def unwrap_state_dict(obj, where: str, key: str | None = None) -> dict[str, np.ndarray]:
  """The U-Net state dict inside what a `.pt` file holds, as float32 arrays.

  Accepts a plain state dict (the official `model*.pt` / `ema_*.pt`), or a dict
  holding one (e.g. {"model": ..., "ema": ..., "step": ...}): `key` picks the entry,
  needed only when several entries are state dicts. A common "module." prefix
  (DataParallel) is removed.

  Raises:
    OfficialCheckpointError: no state dict found, an ambiguous one without `key`, a
      key that is not a string, or a parameter holding NaN or Inf (after the
      conversion to float32).
  """
  if key is not None:
    if not isinstance(obj, dict) or key not in obj:
      found = sorted(map(str, obj)) if isinstance(obj, dict) else type(obj).__name__
      raise OfficialCheckpointError(f"{where}: no entry {key!r} (found {found[:8]})")
    obj = obj[key]
  if not _is_state_dict(obj):
    if not isinstance(obj, dict):
      raise OfficialCheckpointError(f"{where}: holds a {type(obj).__name__}, not a state dict")
    nested = [k for k, v in obj.items() if _is_state_dict(v)]
    if len(nested) != 1:
      raise OfficialCheckpointError(
          f"{where}: expected a U-Net state dict (with {_CANDIDATE_KEYS[0]!r}) or a dict "
          f"holding exactly one; found entries {sorted(map(str, obj))[:8]}"
          + (f", of which {nested} are state dicts: choose one with key=" if nested else "")
      )
    obj = obj[nested[0]]
  names = [k for k in obj if not isinstance(k, str)]
  if names:
    raise OfficialCheckpointError(
        f"{where}: the state dict has a key {names[0]!r} of type "
        f"{type(names[0]).__name__}; parameter names are strings"
    )
  if all(k.startswith("module.") for k in obj):
    obj = {k.removeprefix("module."): v for k, v in obj.items()}
  state = {k: np.asarray(v, np.float32) for k, v in obj.items()}
  bad = [k for k, v in state.items() if not np.isfinite(v).all()]
  if bad:
    raise OfficialCheckpointError(
        f"{where}: parameter {bad[0]} holds NaN or Inf values"
        + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else "")
    )
  return state


def _shape(state, name: str, ndim: int, where: str) -> tuple[int, ...]:
  """The shape of parameter `name`, checked to have `ndim` non-zero dimensions."""
  shape = state[name].shape
  if len(shape) != ndim or 0 in shape:
    raise OfficialCheckpointError(
        f"{where}: parameter {name} has shape {shape}; expected " f"{ndim} non-zero dimensions"
    )
  return shape


def _block_indices(state, prefix: str) -> list[int]:
  indices = set()
  for k in state:
    part = k[len(prefix) + 1 :].split(".")[0] if k.startswith(prefix + ".") else None
    if part is not None and not part.isdigit():
      raise OfficialCheckpointError(f"parameter {k}: {part!r} is not a block index")
    if part is not None:
      indices.add(int(part))
  return sorted(indices)


def unet_config(
    state: dict[str, np.ndarray], num_heads: int = OFFICIAL_NUM_HEADS, where: str = "state dict"
) -> UNetConfig:
  """The `UNetConfig` of an official state dict: Q from the label embedding, widths,
  levels, residual blocks per level and attention levels from the layer shapes.

  Raises:
    OfficialCheckpointError: a parameter missing or of a shape no official U-Net has.
    NumHeadsError: `num_heads` does not divide the attention blocks' channels.
  """
  missing = [k for k in _CANDIDATE_KEYS + ("out.2.weight",) if k not in state]
  if missing:
    raise OfficialCheckpointError(f"{where}: not an official U-Net state dict; missing {missing}")
  ch, in_ch, _ = _shape(state, "input_blocks.0.0.weight", 3, where)
  emb, _ = _shape(state, "time_embed.0.weight", 2, where)
  out_ch, _, _ = _shape(state, "out.2.weight", 3, where)
  rows, _ = _shape(state, "label_emb.weight", 2, where)
  if in_ch != 2 or out_ch != 2:
    raise OfficialCheckpointError(
        f"{where}: the U-Net maps {in_ch} -> {out_ch} channels; expected 2 -> 2 "
        "(learn_sigma=False, controls [a_x, yaw rate])"
    )
  if emb % ch or ch % OFFICIAL_GROUPS or rows < 2:
    raise OfficialCheckpointError(
        f"{where}: {ch} base channels, embedding width {emb}, {rows} label rows; expected a "
        f"multiple of {OFFICIAL_GROUPS}, a multiple of it, and Q + 1 >= 2"
    )
  try:
    inputs = _block_indices(state, "input_blocks")
  except OfficialCheckpointError as e:
    raise OfficialCheckpointError(f"{where}: {e}") from None
  downs = [i for i in inputs if f"input_blocks.{i}.0.op.weight" in state]
  levels = len(downs) + 1
  per_level, rem = divmod(len(inputs) - 1 - len(downs), levels)
  if rem or per_level < 1:
    raise OfficialCheckpointError(
        f"{where}: {len(inputs)} input blocks with {len(downs)} "
        "downsamplings do not form a U-Net of equal levels"
    )
  mults, attention, i = [], [], 1
  for level in range(levels):
    out_name = f"input_blocks.{i}.0.out_layers.3.weight"
    film_name = f"input_blocks.{i}.0.emb_layers.1.weight"
    if out_name not in state or film_name not in state:
      raise OfficialCheckpointError(f"{where}: input_blocks.{i} is not a residual block")
    width = _shape(state, out_name, 3, where)[0]
    if width % ch:
      raise OfficialCheckpointError(
          f"{where}: parameter {out_name} has {width} output "
          f"channels, not a multiple of the {ch} base channels"
      )
    if _shape(state, film_name, 2, where)[0] != 2 * width:
      raise OfficialCheckpointError(
          f"{where}: input_blocks.{i} has no scale-shift FiLM "
          "(use_scale_shift_norm=True is required)"
      )
    mults.append(width // ch)
    if f"input_blocks.{i}.1.qkv.weight" in state:
      attention.append(level)
    i += per_level + (level < levels - 1)
  widths = sorted({ch * mults[level] for level in attention} | {ch * mults[-1]})
  if any(c % num_heads for c in widths):
    raise NumHeadsError(
        f"{where}: the attention blocks have {widths} channels, not all "
        f"divisible by {num_heads} heads"
    )
  try:
    return UNetConfig(
        num_tokens=rows - 1,
        base_channels=ch,
        channel_mult=tuple(mults),
        num_res_blocks=per_level,
        emb_mult=emb // ch,
        attention_levels=tuple(attention),
        num_heads=num_heads,
        groups=OFFICIAL_GROUPS,
        dropout=0.0,
    )
  except ValueError as e:  # e.g. more levels than the padded length allows
    raise OfficialCheckpointError(f"{where}: {e}") from None
