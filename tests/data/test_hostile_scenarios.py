"""Scenarios handed to the pipeline as the wrong kind of array: text, objects, complex
numbers, a plain list, a ragged list or one field of another length each give a
`UserError` that names the field (and the predictor's check, which reads xi, mask, v0 and
psi0 without their dtypes, no longer lets text or complex numbers through)."""

import numpy as np
import pytest

from cvmdx_jax import constants
from cvmdx_jax.data.scenarios import FIELDS, Scenarios
from cvmdx_jax.errors import UserError

M = 4
INPUTS = ("xi", "mask", "v0", "psi0")


def _scenarios(**replace) -> Scenarios:
  fields = {name: np.zeros((M, *shape), dtype) for name, (shape, dtype) in FIELDS.items()}
  fields["v0"] = np.full(M, 20.0, np.float32)
  return Scenarios(**{**fields, **replace})


@pytest.mark.parametrize(
    "field, value, problem",
    [
        ("xi", np.zeros((M, 9, 75, 4)).astype(str), "dtype <U"),
        ("xi", np.zeros((M, 9, 75, 4), object), "dtype object"),
        ("v0", np.full(M, 20 + 1j), "dtype complex128"),
        ("psi0", [0.0, 0.1, [0.2], 0.3], "is not an array"),  # ragged
        ("v0", ["fast"] * M, "dtype <U4"),
    ],
)
def test_inputs_that_are_not_real_numbers_name_the_field(field, value, problem):
  with pytest.raises(UserError, match=rf"field '{field}' .*{problem}"):
    _scenarios(**{field: value}).validate(fields=INPUTS, dtypes=False)


def test_a_list_v0_is_read_as_an_array():
  _scenarios(v0=[20.0] * M).validate(fields=INPUTS, dtypes=False)
  with pytest.raises(UserError, match="field 'v0' is negative"):
    _scenarios(v0=[20.0, -1.0, 3.0, 4.0]).validate(fields=INPUTS, dtypes=False)


@pytest.mark.parametrize("field", ["label", "xi", "v0", "frame"])
def test_one_field_of_another_length_is_the_one_blamed(field):
  shape, dtype = FIELDS[field]
  scenarios = _scenarios(**{field: np.zeros((M + 2, *shape), dtype)})
  assert len(scenarios) == M
  with pytest.raises(UserError, match=rf"field '{field}' has shape \({M + 2},"):
    scenarios.validate()


def test_length_counts_the_fields_not_the_label():
  scenarios = _scenarios(label=np.zeros(1, np.int32))
  assert len(scenarios) == M
  assert len(_scenarios()) == M and len(_scenarios().take(np.arange(2))) == 2
  assert constants.NUM_CLASSES == 3  # labels of the contract: 0, 1, 2
