"""benchmarks.random_models: random scenarios that follow the data contract, seeded."""

import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.benchmarks import random_models


def test_random_scenarios_follow_the_data_contract():
  s = random_models.random_scenarios(5)
  assert s.xi.shape == (5, constants.NUM_VEHICLES, constants.T_OBS, 4)
  assert s.xi.dtype == np.float32 and s.mask.all()
  np.testing.assert_array_equal(s.label, [0, 1, 2, 0, 1])
  np.testing.assert_array_equal(random_models.random_scenarios(5).xi, s.xi)  # seeded
