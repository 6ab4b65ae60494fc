"""`csv_text.table_csv` against pandas' own `to_csv(index=False, float_format="%.2f")`."""

import datetime

import numpy as np
import pandas as pd
import pytest

from cvmdx_jax.data import csv_text


def _pandas(frame: pd.DataFrame) -> str:
  return frame.to_csv(index=False, float_format="%.2f", lineterminator="\n")


def test_floats_ints_bools_and_text_equal_pandas_byte_for_byte():
  """Halves that "%.2f" rounds to even or by their binary value, negative zero and values
  that round to it, NaN (an empty cell), infinities, large magnitudes; many random values."""
  rng = np.random.default_rng(0)
  edges = [0.125, 0.375, 2.675, 1.005, -0.0, -0.004, 0.004, 1e15, -123456.785, 0.5, 1.5]
  edges += [np.nan, np.inf, -np.inf, 1e-300, 99.995, -99.995]
  n = 3000
  floats = np.concatenate(
      [edges, rng.normal(0, 10.0 ** rng.integers(-3, 6, n), n), rng.integers(-9999, 9999, n) / 8]
  )
  m = len(floats)
  frame = pd.DataFrame(
      {
          "x": floats,
          "y32": floats.astype(np.float32),
          "id": rng.integers(-(2**40), 2**40, m),
          "small": rng.integers(0, 255, m).astype(np.uint8),
          "flag": rng.random(m) < 0.5,
          "class": np.where(rng.random(m) < 0.5, "Car", "Truck"),
      }
  )
  text = csv_text.table_csv(frame)
  assert text == _pandas(frame)
  assert "\n-0.00," in text and "\n,nan" not in text  # negative zero kept, NaN empty


@pytest.mark.parametrize(
    "column",
    [
        ["a,b", "c"],  # text pandas quotes
        ['say "x"', "c"],
        ["a", None],  # a missing text cell
        [datetime.datetime(2026, 12, 6), datetime.datetime(2026, 12, 7)],
        pd.array([1, None], dtype="Int64"),  # a nullable extension dtype
    ],
)
def test_cells_pandas_formats_its_own_way_leave_the_table_to_pandas(column):
  frame = pd.DataFrame({"v": [1.234, -5.678], "c": column})
  assert csv_text.table_csv(frame) == _pandas(frame)


def test_empty_tables_equal_pandas():
  assert csv_text.table_csv(pd.DataFrame({"a": [], "b": []})) == _pandas(
      pd.DataFrame({"a": [], "b": []})
  )
  assert csv_text.table_csv(pd.DataFrame()) == _pandas(pd.DataFrame())
