"""Diffusion maths: schedules, parameterisations, loss, guidance and samplers (one entry
point, `get_sampler`, and every sampler by name)."""

from cvmdx_jax.diffusion.distillation import distilled_sample
from cvmdx_jax.diffusion.guidance import (
    combine_eps,
    cond_uncond_v_fn,
    guidance_weight,
    guided_eps,
    guided_v_fn,
    official_step_weights,
)
from cvmdx_jax.diffusion.losses import v_loss
from cvmdx_jax.diffusion.param import (
    eps_from_v,
    eps_from_x0,
    q_sample,
    v_from_eps,
    v_from_x0_eps,
    x0_from_v,
)
from cvmdx_jax.diffusion.sampler import SAMPLER_NAMES, get_sampler
from cvmdx_jax.diffusion.samplers import ddim_sample, ddpm_sample, official_ddim_sample
from cvmdx_jax.diffusion.schedule import (
    Schedule,
    cosine_schedule,
    ddim_timesteps,
    official_ddim_timesteps,
)
from cvmdx_jax.diffusion.solvers import dpmpp_2m_sample

__all__ = [
    "SAMPLER_NAMES",
    "Schedule",
    "combine_eps",
    "cond_uncond_v_fn",
    "cosine_schedule",
    "ddim_sample",
    "ddim_timesteps",
    "ddpm_sample",
    "distilled_sample",
    "dpmpp_2m_sample",
    "eps_from_v",
    "eps_from_x0",
    "get_sampler",
    "guidance_weight",
    "guided_eps",
    "guided_v_fn",
    "official_ddim_sample",
    "official_ddim_timesteps",
    "official_step_weights",
    "q_sample",
    "v_from_eps",
    "v_from_x0_eps",
    "v_loss",
    "x0_from_v",
]
