"""experiments/benchmark_costs.py: the log-log slopes, the PNG and the demo
models it times."""

import io

import numpy as np
import pytest
from PIL import Image

from experiments import benchmark_costs as costs


def _rows(x, y):
  return [{"x": a, "seconds": b, "peak_mib": 2.0 * b} for a, b in zip(x, y)]


def test_slopes_of_power_laws_and_of_a_curve_with_a_floor():
  x = [1, 10, 100, 1000]
  assert np.allclose(costs.slopes(_rows(x, [3.0 * a for a in x]), "seconds"), (1.0, 1.0))
  assert np.allclose(costs.slopes(_rows(x, [a**2 for a in x]), "peak_mib"), (2.0, 2.0))
  # a fixed cost per call, then linear: the upper half shows the linear part
  whole, upper = costs.slopes(_rows(x, [5.0 + a for a in x]), "seconds")
  assert whole < 0.8
  assert abs(upper - np.log(1005 / 105) / np.log(10)) < 1e-9


def test_plot_is_a_small_png():
  png = costs.plot(_rows([9, 16, 32], [0.1, 0.2, 0.4]), "samples N", "title", True)
  image = Image.open(io.BytesIO(png))
  assert image.format == "PNG" and image.size == (378, 270)
  assert len(png) < 100_000


@pytest.mark.slow  # ~50 s on 2 busy cores: the demo U-Net's parameters prepared
def test_demo_predictor_samples_with_the_demo_student():
  predictor = costs.demo_predictor(num_samples=9, chunk=4)
  assert predictor.sampling.num_samples == 9 and predictor.chunk_size == 4
  assert predictor.sampling.sampler == "distilled" and predictor.sampling.steps == 2
  assert predictor.denoiser.config.diffusion.guidance_input
