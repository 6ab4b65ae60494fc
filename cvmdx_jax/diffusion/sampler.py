"""One entry point to the x0 samplers of a v-prediction model (score_sde's `get_sampling_fn`
idea): `get_sampler` binds a sampler's settings and returns one function of the same
signature for all of them.

    sample = get_sampler("dpmpp2m", steps=3, clip_x0=1.0)
    x0 = sample(v_fn, key, (n, 125, 2), schedule)

`v_fn(x_t, t)` is the (guided) velocity; the official code's guided DDIM loop combines its
two branches itself and stays `samplers.official_ddim_sample`.
"""

import functools
from collections.abc import Callable

from cvmdx_jax.diffusion.distillation import distilled_sample
from cvmdx_jax.diffusion.samplers import ddim_sample, ddpm_sample
from cvmdx_jax.diffusion.solvers import dpmpp_2m_sample
from cvmdx_jax.errors import UserError

# name -> (steps, eta, clip_x0) -> sample(v_fn, key, shape, schedule)
_SAMPLERS = {
    "ddim": lambda steps, eta, clip_x0: functools.partial(
        ddim_sample, steps=steps, eta=eta, clip_x0=clip_x0
    ),
    "ddpm": lambda steps, eta, clip_x0: functools.partial(ddpm_sample, clip_x0=clip_x0),
    "dpmpp2m": lambda steps, eta, clip_x0: functools.partial(
        dpmpp_2m_sample, steps=steps, clip_x0=clip_x0
    ),
    "distilled": lambda steps, eta, clip_x0: functools.partial(
        distilled_sample, steps=steps, clip_x0=clip_x0
    ),
}
SAMPLER_NAMES = tuple(_SAMPLERS)


def get_sampler(
    name: str, *, steps: int, eta: float = 0.0, clip_x0: float | None = None
) -> Callable:
  """The sampler `name` with its settings bound: sample(v_fn, key, shape, schedule) -> x0.

  Args:
    name: "ddim" (S steps, noise eta), "ddpm" (all T steps; steps and eta unused),
      "dpmpp2m" (DPM-Solver++(2M), S evaluations) or "distilled" (a distilled student's
      deterministic DDIM, S evaluations).
    steps: S.
    eta: DDIM noise (0 = deterministic); "ddim" only.
    clip_x0: clip predicted x0 to [-clip_x0, clip_x0]; None = no clipping.

  Raises:
    UserError: an unknown name.
  """
  if name not in _SAMPLERS:
    raise UserError(f"sampler must be one of {SAMPLER_NAMES}, got {name!r}")
  return _SAMPLERS[name](steps, eta, clip_x0)
