"""experiments/sampler_pareto.py: choosing the default sampler from a Pareto table."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from configs import distill as distill_config
from cvmdx_jax.config.runs import DistillRunConfig
from cvmdx_jax.train import distill
from experiments import sampler_pareto
from tests.subprocess_env import environ


def _row(sampler, steps, ade):
  return {
      "sampler": sampler,
      "steps": steps,
      "evaluations": 2 * steps,
      "mean_ade": ade,
      "mean_fde": 3 * ade,
      "min_ade_k": ade - 0.1,
      "min_fde_k": 3 * ade - 0.2,
  }


ROWS = [
    _row("ddim", 2, 1.30),
    _row("ddim", 5, 1.03),
    _row("ddim", 10, 1.00),
    _row("dpmpp2m", 3, 1.025),
    _row("dpmpp2m", 4, 1.019),
    _row("dpmpp2m", 5, 1.01),
]


def test_fewest_evaluations_within_the_tolerance():
  # bound 1.02: dpmpp2m 3 (1.025) is out, dpmpp2m 4 (1.019, 8 evals) is the cheapest in
  assert sampler_pareto.choose_default(ROWS, 0.02) is ROWS[4]
  # a looser bound admits dpmpp2m 3; ties in evaluations go to the lower ADE
  assert sampler_pareto.choose_default(ROWS, 0.03) is ROWS[3]
  tie = ROWS + [_row("ddim", 3, 1.02)]
  assert sampler_pareto.choose_default(tie, 0.03) is tie[-1]
  # zero tolerance: only settings at least as good as DDIM-10 (here itself)
  assert sampler_pareto.choose_default(ROWS, 0.0) is ROWS[2]


def test_every_criterion_must_hold():
  # dpmpp2m 4 is within 2 % in mean ADE but its best-of-K FDE is 5 % worse than DDIM-10's
  rows = [dict(r) for r in ROWS]
  rows[4]["min_fde_k"] = 1.05 * rows[2]["min_fde_k"]
  assert sampler_pareto.choose_default(rows, 0.02) is rows[4]
  assert sampler_pareto.choose_default(rows, 0.02, ("mean_ade", "min_fde_k")) is rows[5]


def test_reference_must_be_evaluated():
  with pytest.raises(ValueError, match="reference"):
    sampler_pareto.choose_default(ROWS[:2], 0.02)


def test_markdown_marks_the_choice_and_sorts_by_cost():
  table = sampler_pareto.markdown(ROWS, ROWS[4], 0.02, "note").splitlines()
  body = [r for r in table if r.startswith("| ddim") or r.startswith("| dpmpp2m")]
  assert [r.split("|")[3].strip() for r in body] == ["4", "6", "8", "10", "10", "20"]
  assert "**(default)**" in body[2] and sum("default" in r for r in body) == 1
  assert "dpmpp2m S = 4" in table[-1] and "chosen on val" in table[-1]


def test_rows_carry_their_relative_difference_to_the_reference_with_an_interval():
  rng = np.random.default_rng(0)
  base = {c: rng.gamma(4.0, 0.25, 40) for c in sampler_pareto.COLUMNS}
  rows = [dict(ROWS[2]), dict(ROWS[4])]  # the reference first, then dpmpp2m 4
  per_scenario = [base, {c: 1.05 * v for c, v in base.items()}]
  groups = np.repeat(np.arange(20), 2)  # two windows of each of 20 vehicles
  sampler_pareto.against_reference(per_scenario, rows, groups)
  for c in sampler_pareto.COLUMNS:  # 5 % worse in every scenario: in every replicate too
    got = rows[1]["vs_reference"][c]
    np.testing.assert_allclose([got["relative"], got["relative_low"], got["relative_high"]], 0.05)
    assert rows[0]["vs_reference"][c]["relative"] == 0.0
  table = sampler_pareto.markdown(rows, rows[1], 0.02, "note")
  assert "| dpmpp2m S = 4 | +5.0 % [+5.0, +5.0] |" in table
  assert "resampling whole vehicles" in table


@pytest.mark.slow
def test_the_script_samples_a_progressive_student_at_its_own_steps(tiny_runs, tmp_path):
  """A progressive student is scored with the teacher's N and its own sampler and steps (the
  teacher's sampler would be refused by the student's step check)."""
  config = distill_config.get_config("tiny")
  config.teacher_dir, config.steps, config.guided_progressive = (
      str(tiny_runs / "diffusion"),
      2,
      True,
  )
  distill.train(DistillRunConfig.from_config(config), tmp_path / "student")
  script = Path(sampler_pareto.__file__)
  subprocess.run(
      [
          sys.executable,
          str(script),
          f"--tokenizer_dir={tiny_runs / 'tokenizer'}",
          f"--diffusion_dir={tiny_runs / 'diffusion'}",
          f"--data_dir={tiny_runs / 'data'}",
          f"--out_dir={tmp_path / 'pareto'}",
          f"--distilled_dirs={tmp_path / 'student'}",
          "--num_scenarios=3",
          "--ddim_steps=10",
          "--dpmpp2m_steps=",
          "--tolerance=10",
      ],
      check=True,
      env=environ(JAX_PLATFORMS="cpu"),
      capture_output=True,
  )
  rows = json.loads((tmp_path / "pareto" / "pareto.json").read_text())["rows"]
  assert [(r["sampler"], r["steps"], r["evaluations"]) for r in rows] == [
      ("ddim", 10, 20),
      ("distilled", 2, 2),
  ]
