"""Official cVMDx checkpoints (PyTorch) -> cvmdx_jax U-Net parameters.

The official model is `improved_diffusion.unet.UNetModel` as built by
`model_and_diffusion_defaults(num_classes=Q + 1, predict_v=True)`; its state dict (a
`model*.pt` or `ema_*.pt` file) names the layers

  time_embed.{0,2}                 Linear (out, in)          -> time_mlp{1,2}
  label_emb                        Embedding (Q + 1, E)      -> token_embed (null = Q)
  input_blocks.0.0                 Conv1d (out, in, k)       -> conv_in
  input_blocks.i.0 / .i.1          ResBlock / AttentionBlock -> down_blocks[j].res / .attn
  input_blocks.i.0.op              stride-2 Conv1d           -> down_samples[level].conv
  middle_block.{0,1,2}             ResBlock, Attention, ResBlock -> mid[0].res, mid[0].attn,
                                                                   mid[1].res
  output_blocks.o.{0,1}            ResBlock / AttentionBlock -> up_blocks[o].res / .attn
  output_blocks.o.{1,2}.conv       Upsample conv             -> up_samples[u].conv
  out.{0,2}                        GroupNorm, Conv1d         -> norm_out, conv_out
  ResBlock: in_layers.{0,2} (norm, conv), emb_layers.1 (FiLM linear), out_layers.{0,3}
    (norm, conv), skip_connection (1x1 conv, where channels change) -> norm1, conv1,
    film, norm2, conv2, skip
  AttentionBlock: norm, qkv (1x1 conv to 3C, ordered per head: [q_h, k_h, v_h] for head
    h = 0..H-1), proj_out (1x1 conv) -> norm, attn.{query,key,value,out}

Layouts: torch Conv1d (out, in, k) -> flax (k, in, out); Linear (out, in) -> (in, out).
The number of attention heads is not stored in a state dict (official default 4).
"""

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.models import torch_zip
from cvmdx_jax.models import unet1d

OFFICIAL_NUM_HEADS = 4
OFFICIAL_GROUPS = 32  # the official GroupNorm32 always uses 32 groups
_CANDIDATE_KEYS = ("label_emb.weight", "time_embed.0.weight", "input_blocks.0.0.weight")


class OfficialCheckpointError(ValueError):
  """A checkpoint that is not a state dict of the official cVMDx U-Net."""


def _is_state_dict(obj) -> bool:
  return (isinstance(obj, dict) and bool(obj)
          and all(isinstance(v, np.ndarray) for v in obj.values())
          and any(k.removeprefix("module.") in _CANDIDATE_KEYS for k in obj))


def unwrap_state_dict(obj, where: str, key: str | None = None) -> dict[str, np.ndarray]:
  """The U-Net state dict inside what a `.pt` file holds, as float32 arrays.

  Accepts a plain state dict (the official `model*.pt` / `ema_*.pt`), or a dict
  holding one (e.g. {"model": ..., "ema": ..., "step": ...}): `key` picks the entry,
  needed only when several entries are state dicts. A common "module." prefix
  (DataParallel) is removed.

  Raises:
    OfficialCheckpointError: no state dict found, or an ambiguous one without `key`.
  """
  if key is not None:
    if not isinstance(obj, dict) or key not in obj:
      found = sorted(obj) if isinstance(obj, dict) else type(obj).__name__
      raise OfficialCheckpointError(f"{where}: no entry {key!r} (found {found})")
    obj = obj[key]
  if not _is_state_dict(obj):
    if not isinstance(obj, dict):
      raise OfficialCheckpointError(f"{where}: holds a {type(obj).__name__}, not a state dict")
    nested = [k for k, v in obj.items() if _is_state_dict(v)]
    if len(nested) != 1:
      raise OfficialCheckpointError(
          f"{where}: expected a U-Net state dict (with {_CANDIDATE_KEYS[0]!r}) or a dict "
          f"holding exactly one; found entries {sorted(map(str, obj))}"
          + (f", of which {nested} are state dicts: choose one with key=" if nested else ""))
    obj = obj[nested[0]]
  if all(k.startswith("module.") for k in obj):
    obj = {k.removeprefix("module."): v for k, v in obj.items()}
  return {k: np.asarray(v, np.float32) for k, v in obj.items()}


def _block_indices(state, prefix: str) -> list[int]:
  return sorted({int(k.split(".")[1]) for k in state if k.startswith(prefix + ".")})


def unet_config(state: dict[str, np.ndarray], num_heads: int = OFFICIAL_NUM_HEADS,
                where: str = "state dict") -> unet1d.UNetConfig:
  """The `UNetConfig` of an official state dict: Q from the label embedding, widths,
  levels, residual blocks per level and attention levels from the layer shapes."""
  missing = [k for k in _CANDIDATE_KEYS + ("out.2.weight",) if k not in state]
  if missing:
    raise OfficialCheckpointError(f"{where}: not an official U-Net state dict; missing {missing}")
  ch, in_ch, _ = state["input_blocks.0.0.weight"].shape
  emb = state["time_embed.0.weight"].shape[0]
  out_ch = state["out.2.weight"].shape[0]
  if in_ch != 2 or out_ch != 2:
    raise OfficialCheckpointError(
        f"{where}: the U-Net maps {in_ch} -> {out_ch} channels; expected 2 -> 2 "
        "(learn_sigma=False, controls [a_x, yaw rate])")
  if emb % ch:
    raise OfficialCheckpointError(f"{where}: embedding width {emb} is not a multiple of {ch}")
  inputs = _block_indices(state, "input_blocks")
  downs = [i for i in inputs if f"input_blocks.{i}.0.op.weight" in state]
  levels = len(downs) + 1
  per_level, rem = divmod(len(inputs) - 1 - len(downs), levels)
  if rem or per_level < 1:
    raise OfficialCheckpointError(f"{where}: {len(inputs)} input blocks with {len(downs)} "
                                  "downsamplings do not form a U-Net of equal levels")
  mults, attention, i = [], [], 1
  for level in range(levels):
    out_w = state.get(f"input_blocks.{i}.0.out_layers.3.weight")
    film = state.get(f"input_blocks.{i}.0.emb_layers.1.weight")
    if out_w is None or film is None or out_w.shape[0] % ch:
      raise OfficialCheckpointError(f"{where}: input_blocks.{i} is not a residual block")
    if film.shape[0] != 2 * out_w.shape[0]:
      raise OfficialCheckpointError(f"{where}: input_blocks.{i} has no scale-shift FiLM "
                                    "(use_scale_shift_norm=True is required)")
    mults.append(out_w.shape[0] // ch)
    if f"input_blocks.{i}.1.qkv.weight" in state:
      attention.append(level)
    i += per_level + (level < levels - 1)
  return unet1d.UNetConfig(num_tokens=state["label_emb.weight"].shape[0] - 1,
                           base_channels=ch, channel_mult=tuple(mults),
                           num_res_blocks=per_level, emb_mult=emb // ch,
                           attention_levels=tuple(attention), num_heads=num_heads,
                           groups=OFFICIAL_GROUPS, dropout=0.0)


def _conv(w, b):
  return {"kernel": np.transpose(w, (2, 1, 0)), "bias": b}


def _attention(state, p: str, heads: int) -> dict[str, np.ndarray]:
  w, b = state[f"{p}.qkv.weight"][:, :, 0], state[f"{p}.qkv.bias"]
  c = w.shape[1]
  d = c // heads
  w = w.reshape(heads, 3, d, c)  # (head, q/k/v, head dim, in)
  b = b.reshape(heads, 3, d)
  out = {f"norm.{n}": state[f"{p}.norm.{m}"] for n, m in (("scale", "weight"), ("bias", "bias"))}
  for s, name in enumerate(("query", "key", "value")):
    out[f"attn.{name}.kernel"] = np.transpose(w[:, s], (2, 0, 1))  # (in, head, head dim)
    out[f"attn.{name}.bias"] = b[:, s]
  proj = state[f"{p}.proj_out.weight"][:, :, 0]  # (out, head * head dim)
  out["attn.out.kernel"] = np.transpose(proj.reshape(proj.shape[0], heads, d), (1, 2, 0))
  out["attn.out.bias"] = state[f"{p}.proj_out.bias"]
  return out


def _converted(state, cfg: unet1d.UNetConfig) -> tuple[dict[str, np.ndarray], set[str]]:
  """{our parameter path: array} and the official names used."""
  out, used = {}, set()

  def get(name):
    used.add(name)
    if name not in state:
      raise OfficialCheckpointError(f"official parameter {name} missing from the state dict")
    return state[name]

  def put(ours, arrays):
    out.update({f"{ours}.{k}": v for k, v in arrays.items()})

  conv = lambda p: _conv(get(f"{p}.weight"), get(f"{p}.bias"))
  linear = lambda p: {"kernel": get(f"{p}.weight").T, "bias": get(f"{p}.bias")}
  norm = lambda p: {"scale": get(f"{p}.weight"), "bias": get(f"{p}.bias")}

  def res(p, ours):
    put(f"{ours}.norm1", norm(f"{p}.in_layers.0"))
    put(f"{ours}.conv1", conv(f"{p}.in_layers.2"))
    put(f"{ours}.film", linear(f"{p}.emb_layers.1"))
    put(f"{ours}.norm2", norm(f"{p}.out_layers.0"))
    put(f"{ours}.conv2", conv(f"{p}.out_layers.3"))
    if f"{p}.skip_connection.weight" in state:
      put(f"{ours}.skip", conv(f"{p}.skip_connection"))

  def attn(p, ours):
    for n in ("norm.weight", "norm.bias", "qkv.weight", "qkv.bias", "proj_out.weight",
              "proj_out.bias"):
      get(f"{p}.{n}")
    put(ours, _attention(state, p, cfg.num_heads))

  put("time_mlp1", linear("time_embed.0"))
  put("time_mlp2", linear("time_embed.2"))
  out["token_embed.embedding"] = get("label_emb.weight")
  put("conv_in", conv("input_blocks.0.0"))
  levels, i, d = len(cfg.channel_mult), 1, 0
  for level in range(levels):
    for _ in range(cfg.num_res_blocks):
      res(f"input_blocks.{i}.0", f"down_blocks.{d}.res")
      if level in cfg.attention_levels:
        attn(f"input_blocks.{i}.1", f"down_blocks.{d}.attn")
      i, d = i + 1, d + 1
    if level < levels - 1:
      put(f"down_samples.{level}.conv", conv(f"input_blocks.{i}.0.op"))
      i += 1
  res("middle_block.0", "mid.0.res")
  attn("middle_block.1", "mid.0.attn")
  res("middle_block.2", "mid.1.res")
  o, u = 0, 0
  for level in reversed(range(levels)):
    for j in range(cfg.num_res_blocks + 1):
      res(f"output_blocks.{o}.0", f"up_blocks.{o}.res")
      k = 1
      if level in cfg.attention_levels:
        attn(f"output_blocks.{o}.1", f"up_blocks.{o}.attn")
        k = 2
      if level and j == cfg.num_res_blocks:
        put(f"up_samples.{u}.conv", conv(f"output_blocks.{o}.{k}.conv"))
        u += 1
      o += 1
  put("norm_out", norm("out.0"))
  put("conv_out", conv("out.2"))
  return out, used


def _path_name(path) -> str:
  parts = [str(getattr(p, "key", getattr(p, "idx", getattr(p, "name", p)))) for p in path]
  return ".".join(parts[:-1] if parts and parts[-1] == "value" else parts)


def params_from_state_dict(state: dict[str, np.ndarray], cfg: unet1d.UNetConfig,
                           where: str = "state dict"):
  """The U-Net parameters (the pytree of `unet1d.init_unet(cfg, key)[1]`).

  Raises:
    OfficialCheckpointError: a parameter missing, left over, or of another shape.
  """
  abstract = jax.eval_shape(lambda: unet1d.init_unet(cfg, jax.random.key(0))[1])
  try:
    arrays, used = _converted(state, cfg)
  except OfficialCheckpointError as e:
    raise OfficialCheckpointError(f"{where}: {e}") from None
  unused = sorted(set(state) - used)
  if unused:
    raise OfficialCheckpointError(f"{where}: parameters not part of the U-Net: {unused[:8]}")
  problems = []

  def fill(path, leaf):
    name = _path_name(path)
    value = arrays.pop(name, None)
    if value is None or value.shape != leaf.shape:
      problems.append(f"{name}: expected {leaf.shape}, got "
                      f"{None if value is None else value.shape}")
      return jnp.zeros(leaf.shape, leaf.dtype)
    return jnp.asarray(value, leaf.dtype)

  params = jax.tree_util.tree_map_with_path(fill, abstract)
  problems += [f"{name}: no such parameter in the U-Net" for name in sorted(arrays)]
  if problems:
    raise OfficialCheckpointError(f"{where}: does not match the official U-Net layout: "
                                  + "; ".join(problems[:8]))
  return params


def load_official(path, *, key: str | None = None, num_heads: int = OFFICIAL_NUM_HEADS):
  """(UNetConfig, params) of an official `.pt` checkpoint (read without torch)."""
  state = unwrap_state_dict(torch_zip.read_pt(path), str(path), key)
  cfg = unet_config(state, num_heads, str(path))
  return cfg, params_from_state_dict(state, cfg, str(path))
