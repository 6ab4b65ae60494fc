"""The checks of a `Predictor` call's inputs before anything runs: the seed, the scenarios
against the highD reader's bounds (`check_inputs`), and a progressive student's sampling
settings against those it was distilled for (`check_student_steps`)."""

import math
import warnings

import numpy as np

from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.data import highd_checks, highd_format
from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.errors import UserError


class UnusualScenarioWarning(UserWarning):
  """Some scenarios hold an ego state at t0 that the highD reader would not produce."""


INPUT_FIELDS = ("xi", "mask", "v0", "psi0")  # the Scenarios fields a prediction reads
# The reader's bounds on the ego velocity at t0 (road frame, m/s): x along travel in
# [-MAX_DIRECTION_SLACK, 100], |y| <= 20; v0 = |velocity| <= hypot(100, 20).
_VX = (-highd_checks.MAX_DIRECTION_SLACK, highd_format.RANGES["tracks"]["xVelocity"][1])
_VY = highd_format.RANGES["tracks"]["yVelocity"][1]
MAX_V0 = math.hypot(_VX[1], _VY)
_PI32 = float(np.float32(math.pi))  # pi as float32 holds it (slightly above math.pi)


def _first(bad) -> int:
  return int(np.flatnonzero(bad)[0])


def check_inputs(scenarios: Scenarios, seed) -> None:
  """Checks a `Predictor` call's inputs.

  Raises:
    ValueError: `seed` not an int in [0, 2**32) (bools refused; `jax.random.key` would
      wrap larger ones); a field of `INPUT_FIELDS` of the wrong shape or not finite, or
      M = 0 (`Scenarios.validate`); for the first such scenario: the ego absent at t0
      (field 'mask', [:, 0, -1]), |psi0| > pi, v0 < 0 or v0 > MAX_V0 m/s.
  Warns:
    UnusualScenarioWarning: ego velocity at t0 with an along-road component below
      -MAX_DIRECTION_SLACK m/s or a lateral one beyond 20 m/s (the reader refuses such rows;
      the model never saw them); names the first such scenario.
  """
  if not isinstance(seed, (int, np.integer)) or isinstance(seed, (bool, np.bool_)):
    raise UserError(f"seed={seed!r}: expected an int in [0, 2**32)")
  if not 0 <= seed < 2**32:
    raise UserError(f"seed={seed}: must be in [0, 2**32)")
  scenarios.validate(fields=INPUT_FIELDS, dtypes=False, allow_empty=False)
  mask, v0, psi0 = (
      np.asarray(scenarios.mask),
      np.asarray(scenarios.v0, np.float64),
      np.asarray(scenarios.psi0, np.float64),
  )
  if not mask[:, 0, -1].all():
    raise UserError(
        f"scenarios: field 'mask' marks the ego absent at t0 (mask[i, 0, -1]), "
        f"scenario {_first(~mask[:, 0, -1])}"
    )
  for name, value, bad, bound in (
      ("psi0", psi0, np.abs(psi0) > _PI32, "|psi0| <= pi rad"),
      ("v0", v0, v0 > MAX_V0, f"v0 <= {MAX_V0:.4g} m/s"),
  ):
    if bad.any():
      i = _first(bad)
      raise UserError(
          f"scenarios: field '{name}' = {value[i]:.6g} (scenario {i}) outside the "
          f"highD reader's range, {bound}"
      )
  vx, vy = v0 * np.cos(psi0), v0 * np.sin(psi0)
  odd = (vx < _VX[0]) | (np.abs(vy) > _VY)
  if odd.any():
    i = _first(odd)
    warnings.warn(
        f"{int(odd.sum())} scenarios have an ego velocity at t0 the highD reader "
        f"refuses (along the road >= {_VX[0]:g} m/s, |lateral| <= {_VY:g} m/s): "
        f"first scenario {i}, v0={v0[i]:.4g} m/s, psi0={psi0[i]:.4g} rad",
        UnusualScenarioWarning,
        stacklevel=3,
    )


PROGRESSIVE_STAGES = ("progressive", "guided_progressive")


def check_student_steps(sampling: SamplingConfig, fingerprint) -> None:
  """A progressive student samples only as it was distilled: the distilled sampler at its
  `steps` (its fingerprint's `distill`); UserError otherwise. Other denoisers pass."""
  distill = dict(fingerprint).get("distill") if fingerprint is not None else None
  if not distill or distill.get("stage") not in PROGRESSIVE_STAGES:
    return
  if sampling.sampler != "distilled" or sampling.steps != distill["steps"]:
    raise UserError(
        f"this student was distilled ({distill['stage']}) to sample in {distill['steps']} "
        f"steps with the 'distilled' sampler; sampling.sampler={sampling.sampler!r}, "
        f"sampling.steps={sampling.steps} would draw from another distribution: drop the "
        "sampler / steps overrides"
    )
