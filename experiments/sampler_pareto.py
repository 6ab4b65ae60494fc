"""Network evaluations against accuracy: DDIM and DPM-Solver++(2M) at several step
counts on one trained run's validation split, and the distilled students of it
(`experiments/distill.py`); picks the default sampler.

  .venv/bin/python experiments/sampler_pareto.py \\
      --tokenizer_dir=runs/demo/tokenizer --diffusion_dir=runs/demo/diffusion \\
      --distilled_dirs=runs/demo/distill_guidance,runs/demo/distill \\
      --data_dir=runs/demo/data --out_dir=runs/demo/pareto

Every setting samples the same class-balanced scenarios with the same seed, the run's own
guidance (paper mode), number of samples and hypothesis method. U-Net evaluations per
sample = 2 S for the guided pair (conditional and unconditional branch per step), S for a
student (w is its input); a student runs the distilled sampler at its own steps (a
guidance student also at --guidance_student_steps). The chosen default is the setting with the
fewest
evaluations whose --criteria (default: mean ADE / FDE and best-of-K ADE / FDE) are all
within --tolerance of the reference's (the paper's DDIM-10): with mean ADE alone, a
2-step solver wins while its samples collapse (best-of-K 3 % worse; BUILD_NOTES.md).
Writes <out_dir>/pareto.md and pareto.json; --from_json re-tabulates a pareto.json.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from absl import flags

from cvmdx_jax.data import dataset
from cvmdx_jax.errors import UserError
from cvmdx_jax.evaluation import intervals, scoring
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.storage import atomic

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion run directory.")
_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory.")
_OUT = flags.DEFINE_string("out_dir", None, "Where pareto.md and pareto.json go.")
_SPLIT = flags.DEFINE_string("split", "val", "Split to evaluate (choose on val).")
_NUM = flags.DEFINE_integer(
    "num_scenarios", 300, "Class-balanced subset size (0 = all).", lower_bound=0
)
_SEED = flags.DEFINE_integer("seed", 0, "Sampling and subset seed.")
_DDIM = flags.DEFINE_list("ddim_steps", ["1", "2", "3", "5", "10", "20"], "DDIM step counts.")
_DPM = flags.DEFINE_list(
    "dpmpp2m_steps", ["2", "3", "4", "5", "6", "8", "10"], "DPM-Solver++(2M) step counts."
)
_TOL = flags.DEFINE_float(
    "tolerance", 0.02, "Allowed relative loss vs the reference.", lower_bound=0.0
)
_CRITERIA = flags.DEFINE_list(
    "criteria",
    ["mean_ade", "mean_fde", "min_ade_k", "min_fde_k"],
    "Errors that must stay within --tolerance of the reference's.",
)
_DISTILLED = flags.DEFINE_list(
    "distilled_dirs",
    [],
    "Distilled student run directories " "(experiments/distill.py) of --diffusion_dir.",
)
_STUDENT_STEPS = flags.DEFINE_list(
    "guidance_student_steps",
    ["1", "2", "4"],
    "Distilled-sampler steps of a guidance student (a "
    "progressive student runs at its own steps).",
)
_FROM_JSON = flags.DEFINE_string(
    "from_json",
    None,
    "Re-tabulate the rows of this pareto.json "
    "(no sampling; the run flags only name the output).",
)
REFERENCE = ("ddim", 10)  # the paper's sampler
COLUMNS = ("mean_ade", "mean_fde", "min_ade_k", "min_fde_k", "brier_min_fde", "energy_score")


def reference_index(rows: list[dict], reference=REFERENCE) -> int:
  """The index of the row of the `reference` (sampler, steps); UserError where none is."""
  for i, r in enumerate(rows):
    if (r["sampler"], r["steps"]) == reference:
      return i
  raise UserError(f"sampler_pareto: the reference setting {reference} was not evaluated")


def choose_default(
    rows: list[dict], tolerance: float, criteria=("mean_ade",), reference=REFERENCE
) -> dict:
  """The row with the fewest evaluations per sample (then the lowest mean ADE) whose
  errors in `criteria` are each <= (1 + tolerance) x the reference row's.

  Raises:
    ValueError: no row is the reference setting.
  """
  ref = rows[reference_index(rows, reference)]
  ok = lambda r: all(r[c] <= (1.0 + tolerance) * ref[c] for c in criteria)
  return min(filter(ok, rows), key=lambda r: (r["evaluations"], r["mean_ade"]))


def markdown(
    rows: list[dict], choice: dict, tolerance: float, note: str, criteria=("mean_ade",)
) -> str:
  """The Pareto table, one row per setting, the chosen one marked."""
  lines = [
      f"Sampler Pareto: {note}",
      "",
      "| sampler | S | U-Net evals / sample | mean ADE | mean FDE | minADE_K | minFDE_K "
      "| Brier-minFDE | energy score |",
      "|---|---|---|---|---|---|---|---|---|",
  ]
  for r in sorted(rows, key=lambda r: (r["evaluations"], r["sampler"])):
    mark = " **(default)**" if r is choice else ""
    run = f" ({r['run']})" if r.get("run") else ""
    lines.append(
        f"| {r['sampler']}{run}{mark} | {r['steps']} | {r['evaluations']} | "
        + " | ".join(f"{r[c]:.3f}" if c in r else "-" for c in COLUMNS)
        + " |"
    )
  if all("vs_reference" in r for r in rows):
    lines += [
        "",
        f"Against {REFERENCE[0]}-{REFERENCE[1]}: mean / reference - 1, paired 95 % interval "
        "resampling whole vehicles:",
        "",
        "| sampler | " + " | ".join(COLUMNS) + " |",
        "|---|" + "---|" * len(COLUMNS),
    ]
    for r in sorted(rows, key=lambda r: (r["evaluations"], r["sampler"])):
      run = f" ({r['run']})" if r.get("run") else ""
      cells = (r["vs_reference"][c] for c in COLUMNS)
      lines.append(
          f"| {r['sampler']}{run} S = {r['steps']} | "
          + " | ".join(
              f"{100 * v['relative']:+.1f} % [{100 * v['relative_low']:+.1f}, "
              f"{100 * v['relative_high']:+.1f}]"
              for v in cells
          )
          + " |"
      )
  lines += [
      "",
      f"Default: {choice['sampler']} S = {choice['steps']}, the fewest evaluations "
      f"with {', '.join(criteria)} within {100 * tolerance:g} % of "
      f"{REFERENCE[0]}-{REFERENCE[1]} (chosen on val).",
  ]
  return "\n".join(lines) + "\n"


def evaluate(
    predictor: Predictor, data, sampler: str, steps: int, seed: int, run: str = ""
) -> tuple[dict, dict]:
  """Mean errors (m) of one sampler setting on `data` (time: experiments/benchmark.py):
  (the row, {column: (M,) per-scenario values})."""
  p = dataclasses.replace(
      predictor,
      sampling=dataclasses.replace(predictor.sampling, sampler=sampler, steps=steps, mode="paper"),
  )
  out = p(data, seed=seed)
  errors = scoring.cvmdx_errors(out, jnp.asarray(data.future), data.label)
  mean, best = errors["cvmdx_mean"], errors["cvmdx_best_of_k"]
  means = {
      "mean_ade": mean["ade"],
      "mean_fde": mean["fde"],
      "min_ade_k": best["ade"],
      "min_fde_k": best["fde"],
      "brier_min_fde": best["brier_min_fde"],
      "energy_score": mean["energy_score"],
  }
  per_step = 1 if predictor.denoiser.config.diffusion.guidance_input else 2
  row = {
      "sampler": sampler,
      "steps": steps,
      "evaluations": per_step * steps,
      "run": run,
      **{k: float(np.mean(v)) for k, v in means.items()},
  }
  return row, {k: np.asarray(v) for k, v in means.items()}


def against_reference(per_scenario: list[dict], rows: list[dict], groups) -> None:
  """Adds to each row "vs_reference": per column {"relative", "relative_low",
  "relative_high"}, its mean over the reference's minus 1 with the paired 95 % interval
  resampling whole vehicles (`evaluation.intervals`)."""
  ref = reference_index(rows)
  for values, row in zip(per_scenario, rows):
    row["vs_reference"] = {}
    for c in COLUMNS:
      d = intervals.paired_difference(values[c], per_scenario[ref][c], groups)
      row["vs_reference"][c] = {k: d[k] for k in ("relative", "relative_low", "relative_high")}


def sample_rows() -> tuple[list[dict], str]:
  """Evaluates every --ddim_steps / --dpmpp2m_steps setting: (rows, a note on the data)."""
  settings = [("ddim", int(s)) for s in _DDIM.value] + [("dpmpp2m", int(s)) for s in _DPM.value]
  if REFERENCE not in settings:
    raise UserError(f"--ddim_steps must include {REFERENCE[1]} (the reference setting)")
  data = dataset.load_balanced(_DATA.value, _SPLIT.value, _SEED.value, _NUM.value)
  predictor = Predictor.load(_TOKENIZER.value, _DIFFUSION.value)
  runs = [(predictor, sampler, steps, "") for sampler, steps in settings]
  for path in _DISTILLED.value:
    student = Predictor.load(_TOKENIZER.value, path)
    steps = (student.sampling.steps,) if student.denoiser.progressive else _STUDENT_STEPS.value
    # the teacher's N, mode and hypotheses; a student's own sampler (and a progressive
    # student's own steps, the only ones it samples)
    student = dataclasses.replace(
        student,
        sampling=dataclasses.replace(predictor.sampling, sampler="distilled", steps=int(steps[0])),
    )
    runs += [(student, "distilled", int(s), Path(path).name) for s in steps]
  rows, per_scenario = [], []
  for p, sampler, steps, run in runs:
    row, values = evaluate(p, data, sampler, steps, _SEED.value, run)
    rows.append(row)
    per_scenario.append(values)
    print(row, flush=True)
  against_reference(per_scenario, rows, intervals.vehicle_groups(data.recording_id, data.track_id))
  note = (
      f"{_DIFFUSION.value}, split {_SPLIT.value}, {len(data)} class-balanced scenarios, "
      f"seed {_SEED.value}, {predictor.sampling.num_samples} samples"
  )
  return rows, note


def main(argv):
  if len(argv) > 1:
    raise UserError(f"sampler_pareto: unexpected arguments {argv[1:]}")
  # checked here, not by flags.mark_flags_as_required: tests import this module, and a
  # required flag would then break every other absl entry point parsed in that process
  missing = [f.name for f in (_TOKENIZER, _DIFFUSION, _DATA, _OUT) if not f.value]
  if missing:
    raise UserError(f"sampler_pareto: flags {missing} are required")
  unknown = sorted(set(_CRITERIA.value) - set(COLUMNS))
  if unknown:
    raise UserError(f"--criteria: unknown {unknown}; choose from {COLUMNS}")
  if _FROM_JSON.value:
    saved = json.loads(Path(_FROM_JSON.value).read_text())
    rows, note = saved["rows"], saved["note"]
  else:
    rows, note = sample_rows()
  choice = choose_default(rows, _TOL.value, _CRITERIA.value)
  table = markdown(rows, choice, _TOL.value, note, _CRITERIA.value)
  out = Path(_OUT.value)
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_json(
      out / "pareto.json",
      {
          "note": note,
          "tolerance": _TOL.value,
          "criteria": _CRITERIA.value,
          "rows": rows,
          "default": choice,
      },
  )
  atomic.write_text(out / "pareto.md", table)
  print(table)


if __name__ == "__main__":
  cli.run(main)
