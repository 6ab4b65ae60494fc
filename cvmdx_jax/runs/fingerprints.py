"""Fingerprints of runs: what a tokeniser, denoiser or baseline checkpoint belongs to.

They are stored with every checkpoint and compared with `storage.identity.check` on
resume, on loading, and when a denoiser is paired with a tokeniser
(`inference.predictor.Predictor.load`) or a baseline with a tokeniser
(`evaluation.learned_baseline.check_tokenizer`).
"""

import dataclasses

from cvmdx_jax import ego_motion
from cvmdx_jax.config.models import TokenizerConfig
from cvmdx_jax.models import scenario_norm


def tokenizer(model_cfg: TokenizerConfig, dataset_id: str) -> dict:
  """Identity of a tokeniser run, stored with its checkpoints and outputs."""
  return {
      "model": dataclasses.asdict(model_cfg),
      "dataset_id": dataset_id,
      "codebook_size": model_cfg.quantizer.codebook_size,
      "latent_dim": model_cfg.encoder.latent_dim,
      "xi_normalisation": {
          "offset": scenario_norm.XI_OFFSET.tolist(),
          "scale": scenario_norm.XI_SCALE.tolist(),
      },
  }


def tokenizer_checkpoint(tokens_meta: dict) -> dict:
  """{"fingerprint", "step", "params_id"} of the tokeniser checkpoint that made the tokens
  (each None for a denoiser paired with none, e.g. an imported one)."""
  checkpoint = tokens_meta.get("checkpoint", {})
  return {k: checkpoint.get(k) for k in ("fingerprint", "step", "params_id")}


def diffusion(config, dataset_id: str, tokens_meta: dict) -> dict:
  """What a denoiser checkpoint belongs to: the U-Net (`config.model`, sized for the
  tokens), T, the control scale, the dataset, the tokeniser checkpoint and (beyond the
  paper) the ego-motion conditioning, the class weights and the intent conditioning."""
  d = config.diffusion
  return {
      "model": dataclasses.asdict(config.model),
      "num_diffusion_steps": d.num_steps,
      "control_scale": list(d.control_scale),
      "dataset_id": dataset_id,
      "tokenizer": tokenizer_checkpoint(tokens_meta),
      "conditioning": {
          "name": d.conditioning,
          "features": ego_motion.NUM_FEATURES,
          "residual_decay_s": list(d.residual_decay_s),
      },
      "class_weights": list(d.class_weights),
      "intent_conditioning": d.intent_conditioning,
  }


def baseline(config, dataset_id: str, tokens_meta: dict) -> dict:
  """What a baseline checkpoint belongs to: the MLP (`config.model`, sized for the
  tokens), the ego-motion features, the loss, the optimiser and its schedule, the dataset
  and the tokeniser checkpoint. num_epochs is part of it: the cosine schedule spans the
  whole run, so more epochs are another run, not a continuation."""
  train = {
      k: v
      for k, v in dataclasses.asdict(config.train).items()
      if k not in ("checkpoint_every", "keep")
  }
  return {
      "model": dataclasses.asdict(config.model),
      "features": ego_motion.NUM_FEATURES,
      "cls_weight": config.loss.cls_weight,
      "train": train,
      "dataset_id": dataset_id,
      "tokenizer": tokenizer_checkpoint(tokens_meta),
  }
