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

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.models import torch_zip, unet1d
from cvmdx_jax.models.official_state import (
    OFFICIAL_NUM_HEADS,
    OfficialCheckpointError,
    unet_config,
    unwrap_state_dict,
)

_REVERSED = lambda shape: tuple(shape)[::-1]  # our conv / linear kernel -> torch weight
_SAME = tuple


def _attention(state, p: str, heads: int, get) -> dict[str, tuple]:
  """{our name: (official name, our shape -> torch shape, array)} of one attention block."""
  w, b = get(f"{p}.qkv.weight", 3), get(f"{p}.qkv.bias", 1)
  proj, proj_b = get(f"{p}.proj_out.weight", 3), get(f"{p}.proj_out.bias", 1)
  scale, bias = get(f"{p}.norm.weight", 1), get(f"{p}.norm.bias", 1)
  c = w.shape[1]
  want = {
      f"{p}.qkv.weight": (3 * c, c, 1),
      f"{p}.qkv.bias": (3 * c,),
      f"{p}.proj_out.weight": (c, c, 1),
      f"{p}.proj_out.bias": (c,),
      f"{p}.norm.weight": (c,),
      f"{p}.norm.bias": (c,),
  }
  for name, shape in want.items():
    if state[name].shape != shape:
      raise OfficialCheckpointError(
          f"parameter {name} has shape {state[name].shape}; an "
          f"attention block of {c} channels has {shape}"
      )
  if c % heads:
    raise OfficialCheckpointError(f"{p} has {c} channels, not divisible by {heads} heads")
  d = c // heads
  w = w[:, :, 0].reshape(heads, 3, d, c)  # (head, q/k/v, head dim, in)
  b = b.reshape(heads, 3, d)
  qkv_w = lambda shape: (3 * shape[1] * shape[2], shape[0], 1)  # (in, head, d) -> torch
  qkv_b = lambda shape: (3 * shape[0] * shape[1],)
  out = {
      "norm.scale": (f"{p}.norm.weight", _SAME, scale),
      "norm.bias": (f"{p}.norm.bias", _SAME, bias),
  }
  for s, name in enumerate(("query", "key", "value")):
    out[f"attn.{name}.kernel"] = (
        f"{p}.qkv.weight",
        qkv_w,
        np.transpose(w[:, s], (2, 0, 1)),
    )  # (in, head, head dim)
    out[f"attn.{name}.bias"] = (f"{p}.qkv.bias", qkv_b, b[:, s])
  out["attn.out.kernel"] = (
      f"{p}.proj_out.weight",
      lambda shape: (shape[2], shape[0] * shape[1], 1),
      np.transpose(proj[:, :, 0].reshape(c, heads, d), (1, 2, 0)),
  )
  out["attn.out.bias"] = (f"{p}.proj_out.bias", _SAME, proj_b)
  return out


def _conv(get, p: str) -> dict:
  """A Conv1d's kernel (torch (out, in, k) -> ours (k, in, out)) and bias, read by `get`."""
  return {
      "kernel": (f"{p}.weight", _REVERSED, np.transpose(get(f"{p}.weight", 3), (2, 1, 0))),
      "bias": (f"{p}.bias", _SAME, get(f"{p}.bias", 1)),
  }


def _linear(get, p: str) -> dict:
  """A Linear's kernel (torch (out, in) -> ours (in, out)) and bias, read by `get`."""
  return {
      "kernel": (f"{p}.weight", _REVERSED, get(f"{p}.weight", 2).T),
      "bias": (f"{p}.bias", _SAME, get(f"{p}.bias", 1)),
  }


def _norm(get, p: str) -> dict:
  """A GroupNorm's scale and bias, read by `get`."""
  return {
      "scale": (f"{p}.weight", _SAME, get(f"{p}.weight", 1)),
      "bias": (f"{p}.bias", _SAME, get(f"{p}.bias", 1)),
  }


def _converted(state, cfg: UNetConfig) -> tuple[dict[str, tuple], set[str]]:
  """{our parameter path: (official name, our shape -> torch shape, array)} and the
  official names used; each official parameter checked to have the dimensions its
  layer needs before its layout is changed."""
  out, used = {}, set()

  def get(name, ndim):
    used.add(name)
    if name not in state:
      raise OfficialCheckpointError(f"official parameter {name} missing from the state dict")
    if state[name].ndim != ndim:
      raise OfficialCheckpointError(
          f"parameter {name} has shape {state[name].shape}; its " f"layer needs {ndim} dimensions"
      )
    return state[name]

  def put(ours, arrays):
    out.update({f"{ours}.{k}": v for k, v in arrays.items()})

  conv, linear, norm = (functools.partial(f, get) for f in (_conv, _linear, _norm))

  def res(p, ours):
    put(f"{ours}.norm1", norm(f"{p}.in_layers.0"))
    put(f"{ours}.conv1", conv(f"{p}.in_layers.2"))
    put(f"{ours}.film", linear(f"{p}.emb_layers.1"))
    put(f"{ours}.norm2", norm(f"{p}.out_layers.0"))
    put(f"{ours}.conv2", conv(f"{p}.out_layers.3"))
    if f"{p}.skip_connection.weight" in state:
      put(f"{ours}.skip", conv(f"{p}.skip_connection"))

  def attn(p, ours):
    put(ours, _attention(state, p, cfg.num_heads, get))

  put("time_mlp1", linear("time_embed.0"))
  put("time_mlp2", linear("time_embed.2"))
  out["token_embed.embedding"] = ("label_emb.weight", _SAME, get("label_emb.weight", 2))
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


def params_from_state_dict(
    state: dict[str, np.ndarray], cfg: UNetConfig, where: str = "state dict"
):
  """The U-Net parameters (the pytree of `unet1d.init_unet(cfg, key)[1]`); every
  shape is compared with the architecture's (`unet1d.abstract_params`) before any is built.

  Raises:
    OfficialCheckpointError: a parameter missing, left over, or of another shape; the
      message names the file and the official parameter.
  """
  abstract = unet1d.abstract_params(cfg)
  try:
    arrays, used = _converted(state, cfg)
  except OfficialCheckpointError as e:
    raise OfficialCheckpointError(f"{where}: {e}") from None
  unused = sorted(set(state) - used)
  if unused:
    raise OfficialCheckpointError(f"{where}: parameters not part of the U-Net: {unused[:8]}")
  leaves = {
      _path_name(path): leaf for path, leaf in jax.tree_util.tree_flatten_with_path(abstract)[0]
  }
  problems = [
      f"{name}: no such parameter in the U-Net" for name in sorted(set(arrays) - set(leaves))
  ]
  problems += [
      f"{name}: no official parameter maps to it" for name in sorted(set(leaves) - set(arrays))
  ]
  for name, (official, to_torch, value) in arrays.items():
    if name in leaves and value.shape != leaves[name].shape:
      problems.append(
          f"parameter {official} has shape {state[official].shape}; the "
          f"architecture read from the file expects {to_torch(leaves[name].shape)}"
      )
  if problems:
    raise OfficialCheckpointError(
        f"{where}: does not match the official U-Net layout: " + "; ".join(problems[:4])
    )
  return jax.tree_util.tree_map_with_path(
      lambda path, leaf: jnp.asarray(arrays[_path_name(path)][2], leaf.dtype), abstract
  )


def load_official(path, *, key: str | None = None, num_heads: int = OFFICIAL_NUM_HEADS):
  """(UNetConfig, params) of an official `.pt` checkpoint (read without torch).

  Raises:
    TorchFileError, OfficialCheckpointError: the file is refused (its name in the message).
    NumHeadsError: `num_heads` does not divide the attention blocks' channels.
  """
  state = unwrap_state_dict(torch_zip.read_pt(path), str(path), key)
  cfg = unet_config(state, num_heads, str(path))
  return cfg, params_from_state_dict(state, cfg, str(path))
