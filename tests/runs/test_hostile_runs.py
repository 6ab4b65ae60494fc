"""A run directory of another kind where a diffusion run is expected (a baseline run given
as --diffusion_dir or as a distillation teacher) is a `UserError` naming its config.json,
not `KeyError: 'diffusion'`."""

from pathlib import Path

import pytest

from configs import baseline as baseline_config
from cvmdx_jax.config.runs import BaselineRunConfig, DiffusionRunConfig
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference import bundles
from cvmdx_jax.runs import layout, loaders


def _baseline_run(root: Path) -> Path:
  """A directory whose config.json is a baseline run's, written by the trainers' writer."""
  run = root / "baseline"
  layout.write_run_config(run, BaselineRunConfig.from_config(baseline_config.get_config("tiny")))
  return run


@pytest.mark.parametrize(
    "read",
    [
        lambda run: loaders.read_run_config(run, DiffusionRunConfig, "diffusion"),
        bundles.load_denoiser,  # evaluate --diffusion_dir, distill's teacher
    ],
)
def test_a_baseline_run_where_a_diffusion_run_is_expected(tmp_path, read):
  run = _baseline_run(tmp_path)
  with pytest.raises(UserError) as info:
    read(run)
  message = str(info.value)
  assert str(run / layout.CONFIG_JSON) in message
  assert "not the config of a diffusion run" in message and "'diffusion'" in message
