"""`Scenarios.validate(fields=...)` and `balanced_indices`, on hand-made fixtures."""

import numpy as np
import pytest

from cvmdx_jax import constants
from cvmdx_jax.data import scenarios as scenarios_lib


def _scenarios(m: int = 3) -> scenarios_lib.Scenarios:
  shapes = {name: (m, *shape) for name, (shape, _) in scenarios_lib.FIELDS.items()}
  arrays = {name: np.zeros(shape) for name, shape in shapes.items()}
  arrays["label"] = np.arange(m) % constants.NUM_CLASSES
  return scenarios_lib.from_arrays(**arrays)


def _with(s, **changes):
  return scenarios_lib.Scenarios(**{**s.as_dict(), **changes})


PREDICTOR_FIELDS = ("xi", "mask", "v0", "psi0")


def test_default_checks_every_field():
  s = _scenarios()
  assert s.validate() is s
  future = s.future.copy()
  future[2, 5, 1] = np.inf
  with pytest.raises(ValueError, match=r"^split x: field 'future' holds NaN/inf \(scenario 2\)"):
    _with(s, future=future).validate("split x")
  with pytest.raises(ValueError, match="field 'v0' has dtype float64, expected float32"):
    _with(s, v0=s.v0.astype(np.float64)).validate()
  with pytest.raises(ValueError, match="field 'label' outside 0..2"):
    _with(s, label=np.array([0, 3, 1], np.int32)).validate()


def test_named_fields_only():
  s = _scenarios()
  future = s.future.copy()
  future[0] = np.nan
  bad = _with(s, future=future, label=np.array([0, 7, 1], np.int32))
  assert bad.validate(fields=PREDICTOR_FIELDS) is bad  # neither future nor label is read
  xi = s.xi.copy()
  xi[1, 4, 10, 3] = np.nan
  with pytest.raises(ValueError, match=r"scenarios: field 'xi' holds NaN/inf \(scenario 1\)"):
    _with(s, xi=xi).validate(fields=PREDICTOR_FIELDS)
  with pytest.raises(
      ValueError, match=r"field 'mask' has shape \(3, 9, 50\), expected " r"\(3, 9, 75\)"
  ):
    _with(s, mask=s.mask[:, :, :50]).validate(fields=PREDICTOR_FIELDS)
  with pytest.raises(ValueError, match=r"unknown field\(s\) \['speed'\]"):
    s.validate(fields=("xi", "speed"))


def test_dtypes_and_empty_flags():
  s = _scenarios()
  wide = _with(s, xi=s.xi.astype(np.float64), v0=s.v0.astype(np.float64))
  with pytest.raises(ValueError, match="field 'xi' has dtype float64"):
    wide.validate(fields=PREDICTOR_FIELDS)
  assert wide.validate(fields=PREDICTOR_FIELDS, dtypes=False) is wide
  empty = s.take(np.zeros(0, int))
  assert empty.validate() is empty
  with pytest.raises(ValueError, match="^scenarios: no scenarios$"):
    empty.validate(fields=PREDICTOR_FIELDS, allow_empty=False)


LABELS = np.array([0, 0, 1, 0, 2, 2, 0, 1, 2, 0])  # counts kl 5, lcr 2, lcl 3


def test_balanced_indices_undersamples_to_smallest_class():
  index = scenarios_lib.balanced_indices(LABELS, seed=0)
  assert np.all(np.diff(index) > 0)
  np.testing.assert_array_equal(np.bincount(LABELS[index], minlength=3), [2, 2, 2])
  np.testing.assert_array_equal(index[LABELS[index] == 1], [2, 7])  # all of the smallest
  np.testing.assert_array_equal(index, scenarios_lib.balanced_indices(LABELS, seed=0))
  draws = {tuple(scenarios_lib.balanced_indices(LABELS, seed=s)) for s in range(20)}
  assert len(draws) > 1  # the seed matters


def test_balanced_indices_of_a_size():
  index = scenarios_lib.balanced_indices(LABELS, seed=1, size=9)  # 3 per class, lcr has 2
  np.testing.assert_array_equal(np.bincount(LABELS[index], minlength=3), [3, 2, 3])
  four = scenarios_lib.balanced_indices(LABELS, seed=1, size=4)  # 2 per class, first 4 kept
  assert len(four) == 4 and np.all(np.diff(four) > 0)
  assert len(scenarios_lib.balanced_indices(LABELS, seed=1, size=0)) == 0
  only_kl = scenarios_lib.balanced_indices(np.zeros(6, int), seed=0, size=3)
  np.testing.assert_array_equal(np.sort(only_kl), only_kl)
  assert len(only_kl) == 1 and len(scenarios_lib.balanced_indices(np.zeros(6, int), 0)) == 0
