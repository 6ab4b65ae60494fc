"""`predictor_inputs.check_inputs`: seeds like the CLI, scenarios against the reader's bounds."""

import math
import warnings

import numpy as np
import pytest

from cvmdx_jax import constants
from cvmdx_jax.data.scenarios import Scenarios, from_arrays
from cvmdx_jax.inference.predictor_inputs import UnusualScenarioWarning, check_inputs


def _scenarios(m=3, **fields) -> Scenarios:
  base = {
      "xi": np.zeros((m, constants.NUM_VEHICLES, constants.T_OBS, constants.NUM_FEATURES)),
      "mask": np.ones((m, constants.NUM_VEHICLES, constants.T_OBS), bool),
      "future": np.zeros((m, constants.T_PRED, 2)),
      "controls": np.zeros((m, constants.T_PRED, 2)),
      "v0": np.full((m,), 30.0),
      "psi0": np.zeros((m,)),
      "label": np.zeros((m,)),
  }
  return from_arrays(**{**base, **fields})


def test_plain_scenarios_and_seeds_pass_silently():
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    for seed in (0, 7, 2**32 - 1, np.int64(5), np.uint32(2**32 - 1)):
      check_inputs(_scenarios(), seed)
    # the reader's extremes: 100 m/s along the road, 20 m/s lateral, 1 m/s backwards
    check_inputs(
        _scenarios(v0=np.array([100.0, 20.0, 1.0]), psi0=np.array([0.0, math.pi / 2, math.pi])), 0
    )


@pytest.mark.parametrize("seed", [-1, 2**32, 2**40, True, 1.0, "0", None])
def test_seeds_the_cli_refuses_are_refused(seed):
  with pytest.raises(ValueError, match=r"^seed=.*2\*\*32"):
    check_inputs(_scenarios(), seed)


def test_absent_ego_at_t0_names_the_scenario():
  mask = np.ones((3, constants.NUM_VEHICLES, constants.T_OBS), bool)
  mask[2, 0, -1] = False
  with pytest.raises(ValueError, match=r"'mask' marks the ego absent at t0.*scenario 2$"):
    check_inputs(_scenarios(mask=mask), 0)
  mask[:] = True
  mask[1, 0, :-1] = False  # ego seen only at t0, a neighbour absent at t0: both fine
  mask[1, 3, -1] = False
  check_inputs(_scenarios(mask=mask), 0)


@pytest.mark.parametrize(
    "field, values, match",
    [
        ("psi0", [0.0, 100.0, 0.0], r"'psi0' = 100 \(scenario 1\).*\|psi0\| <= pi"),
        ("psi0", [0.0, 0.0, -3.2], r"'psi0' = -3.2 \(scenario 2\)"),
        ("v0", [1e4, 30.0, 30.0], r"'v0' = 10000 \(scenario 0\).*v0 <= 102 m/s"),
        ("v0", [30.0, -1.0, 30.0], r"'v0' is negative .*scenario 1"),
        ("v0", [30.0, np.inf, 30.0], r"'v0' holds NaN/inf \(scenario 1\)"),
    ],
)
def test_values_outside_the_reader_range_name_field_and_scenario(field, values, match):
  with pytest.raises(ValueError, match=match):
    check_inputs(_scenarios(**{field: np.array(values)}), 0)


def test_velocities_the_reader_refuses_by_component_warn():
  # 30 m/s backwards (vx = -30), and 25 m/s straight to the left (vy = 25 > 20)
  for v0, psi0, first in (
      ([30.0, 30.0, 30.0], [0.0, 0.0, math.pi], 2),
      ([30.0, 25.0, 30.0], [0.0, math.pi / 2, 0.0], 1),
  ):
    with pytest.warns(UnusualScenarioWarning, match=rf"1 scenarios .*first scenario {first},"):
      check_inputs(_scenarios(v0=np.array(v0), psi0=np.array(psi0)), 0)
