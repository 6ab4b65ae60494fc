"""How a denoiser is sampled: guidance, hypotheses and sampler settings, and
`check_sampling`, the one check of a sampling config against the denoiser it samples."""

import dataclasses
from typing import ClassVar

from cvmdx_jax import constants
from cvmdx_jax.config.denoiser import DenoiserConfig
from cvmdx_jax.config.fields import (
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    ConfigFieldError,
    check_integers,
    check_ranges,
)
from cvmdx_jax.errors import UserError

FORMS = ("paper", "official")


@dataclasses.dataclass(frozen=True)
class GuidanceConfig:
  """Static guidance settings (paper defaults).

  Attributes:
    w_min: guidance weight floor.
    w_max_base: guidance weight ceiling for a scenario with delta = 0.
    t_c: Mahalanobis distance at which w_max reaches 0.
    form: "paper" (extrapolation (1+w) c - w u) or "official" (u + w (c - u)).
    direction: "paper" (w grows with t) or "official" (w shrinks with t).
  """

  w_min: float = 0.1
  w_max_base: float = 1.0
  t_c: float = 50.0
  form: str = "paper"
  direction: str = "paper"

  def __post_init__(self):
    check_ranges(self, {"w_min": NON_NEGATIVE, "w_max_base": NON_NEGATIVE, "t_c": POSITIVE})
    for name in ("form", "direction"):
      if getattr(self, name) not in FORMS:
        raise UserError(f"guidance.{name} must be one of {FORMS}, got {getattr(self, name)!r}")

  @property
  def off(self) -> bool:
    """w(t, delta) = 0 everywhere: the guided v is one branch (the conditional in the
    "paper" form, the unconditional in the "official" one)."""
    return self.w_min == 0 and self.w_max_base == 0


METHODS = ("bic", "kmeans")


SCALINGS = ("physical", "minmax")


@dataclasses.dataclass(frozen=True)
class HypothesisConfig:
  """Static settings of the hypotheses stage (hashable, static under jit).

  Attributes:
    method: "bic" (the paper's PCA + GMM + BIC over C = 1..c_max; the fields from
      scaling to em_iters apply) or "kmeans" (k-means with K = c_max over the
      trajectories; kmeans_iters and endpoint_weight apply).
    c_max: largest number of components tried (C = 1..c_max); K of "kmeans".
    scaling: 'physical' (x / x_scale, y / y_scale; default) or 'minmax' (the
      paper's literal per-scenario min-max recipe; over-selects with small
      floors, see BUILD_NOTES.md).
    x_scale: metres per unit along the road for 'physical'.
    y_scale: metres per unit across the road for 'physical'.
    pca_dim: number r of principal components (paper: 2; official code: 5).
    reg_covar: covariance floor added to the diagonal, in scaled-and-projected
      units^2 (official code: 9e-5 with pca_dim 5). 1e-2 (~0.7 m laterally)
      recovers the true number of clear modes best among 1e-3..3e-2 (see
      BUILD_NOTES.md). A fit whose likelihood is not finite (possible in
      float32 with tiny floors) gets BIC +inf and is never selected.
    em_iters: EM iterations per fit (fixed; no early stop). 5 to 60 select
      the same C on the benchmark sets; 30 leaves margin for harder ones.
    kmeans_iters: Lloyd steps of "kmeans" (fixed; no early stop).
    endpoint_weight: weight of the final step in the k-means distance, in [0, 1]
      (`kmeans.step_weights`; 0 = mean squared displacement over all steps).
    prob_temperature: p(c) proportional to (share of samples)^prob_temperature over the
      non-empty hypotheses (`hypotheses.temper`); 1 = the paper's share. Below 1 flattens
      the shares toward calibrated probabilities that a hypothesis is the closest
      (temperature scaling on val, `evaluation.prob_calibration`).
  """

  method: str = "bic"
  c_max: int = 3
  scaling: str = "physical"
  x_scale: float = 180.0
  y_scale: float = 7.0
  pca_dim: int = 2
  reg_covar: float = 1e-2
  em_iters: int = 30
  kmeans_iters: int = 10
  endpoint_weight: float = 0.0
  prob_temperature: float = 1.0

  RANGES: ClassVar = {
      "c_max": POSITIVE,
      "x_scale": POSITIVE,
      "y_scale": POSITIVE,
      "pca_dim": POSITIVE,
      "reg_covar": POSITIVE,
      "em_iters": NON_NEGATIVE,
      "kmeans_iters": NON_NEGATIVE,
      "endpoint_weight": FRACTION,
      "prob_temperature": POSITIVE,
  }

  def __post_init__(self):
    if self.method not in METHODS:
      raise UserError(f"HypothesisConfig.method must be one of {METHODS}, got {self.method!r}")
    if self.scaling not in SCALINGS:
      raise UserError(f"HypothesisConfig.scaling must be one of {SCALINGS}, got {self.scaling!r}")
    check_ranges(self, self.RANGES)


SAMPLERS = ("ddim", "ddpm", "dpmpp2m", "distilled")


MODES = ("paper", "official")


# Samples per scenario, far above the paper's N = 9 and the hypothesis sweep's 64: the
# predictor holds chunk_size x N samples and the denoiser's activations at once.
MAX_SAMPLES = 1000


@dataclasses.dataclass(frozen=True)
class SamplingConfig:
  """Static sampling settings (paper defaults); what the denoiser itself is (control scale,
  conditioning) is its `targets.DenoiserConfig`.

  Attributes:
    num_samples: N samples per scenario.
    sampler: "ddim" (S steps), "ddpm" (all T steps, the cVMD way) or "dpmpp2m"
      (DPM-Solver++(2M) over the same guided ODE as DDIM, S network evaluations:
      `diffusion.solvers.dpmpp_2m_sample`; beyond the paper) or "distilled" (a distilled
      student's deterministic DDIM, S evaluations: `diffusion.distillation`; needs a
      denoiser with `guidance_input`). A guidance student (`DenoiserConfig.guidance_input`)
      takes w as an input: every sampler then spends one evaluation per step, not two.
    mode: "paper" (the paper's equations) or "official" (the official code's guided
      DDIM loop: `diffusion.official_ddim_sample`, S - 1 updates, weights from
      guidance.w_min to guidance.w_max_base over the step index, no delta).
    steps: S, DDIM, DPM-Solver++(2M) or distilled steps (guided evaluations per sample).
    eta: DDIM noise (0 = deterministic).
    clip_x0: clip predicted x0 to [-clip_x0, clip_x0] in normalised units (the
      official sampler clips to [-1, 1]); None or 0 = no clipping.
    guidance: `GuidanceConfig`.
    hypotheses: `HypothesisConfig`.
    intent_prior: weights (keep lane, lcr, lcl) that multiply an intent conditioning's
      class probabilities before its draws, renormalised: the ratio of the class shares
      where the model is used to those of its train split (all 1: as trained).
  """

  num_samples: int = 9
  sampler: str = "ddim"
  mode: str = "paper"
  steps: int = 10
  eta: float = 0.0
  clip_x0: float | None = 1.0
  guidance: GuidanceConfig = GuidanceConfig()
  hypotheses: HypothesisConfig = HypothesisConfig()
  intent_prior: tuple[float, ...] = (1.0,) * constants.NUM_CLASSES

  def __post_init__(self):
    object.__setattr__(self, "intent_prior", tuple(float(w) for w in self.intent_prior))
    check_integers(self, ("num_samples", "steps"))
    check_ranges(
        self,
        {
            "num_samples": POSITIVE,
            "steps": POSITIVE,
            "eta": NON_NEGATIVE,
            "clip_x0": NON_NEGATIVE,
            "intent_prior": POSITIVE,
        },
    )
    if self.num_samples > MAX_SAMPLES:
      raise ConfigFieldError(
          "num_samples",
          self.num_samples,
          f"must be <= {MAX_SAMPLES} " "(the samples of one chunk of scenarios are held at once)",
      )
    if self.hypotheses.c_max > self.num_samples:
      raise ConfigFieldError(
          "hypotheses.c_max",
          self.hypotheses.c_max,
          f"must be <= num_samples={self.num_samples} (components are " "fitted to the samples)",
      )
    if len(self.intent_prior) != constants.NUM_CLASSES:
      raise ConfigFieldError(
          "intent_prior",
          self.intent_prior,
          f"needs {constants.NUM_CLASSES} weights (keep lane, lcr, lcl)",
      )
    if self.clip_x0 == 0:  # the config's "0 = off"
      object.__setattr__(self, "clip_x0", None)
    if self.sampler not in SAMPLERS:
      raise UserError(f"sampling.sampler must be one of {SAMPLERS}, got {self.sampler!r}")
    if self.mode not in MODES or (self.mode == "official" and self.sampler != "ddim"):
      raise UserError(
          f"sampling.mode must be one of {MODES} ('official' with sampler "
          f"'ddim'), got {self.mode!r} with {self.sampler!r}"
      )


def check_sampling(config: SamplingConfig, denoiser: DenoiserConfig) -> None:
  """The one check that `config` can sample a denoiser of `denoiser`: the official mode
  needs the guided pair (no guidance student), the distilled sampler a guidance student,
  an intent prior other than 1 a denoiser that draws maneuver classes.

  Raises:
    UserError: the mode or sampler does not fit the denoiser.
    ConfigFieldError: sampling.intent_prior set for a denoiser without intent conditioning.
  """
  if denoiser.guidance_input and config.mode == "official":
    raise UserError(
        "sampling.mode 'official' runs the guided pair; a distilled denoiser "
        "(guidance_input) has none: use mode 'paper'"
    )
  if config.sampler == "distilled" and not denoiser.guidance_input:
    raise UserError(
        "sampling.sampler 'distilled' needs a distilled denoiser "
        "(experiments/distill.py); this one is not"
    )
  if not denoiser.intent_conditioning and any(w != 1 for w in config.intent_prior):
    raise ConfigFieldError(
        "sampling.intent_prior",
        config.intent_prior,
        "this denoiser draws no maneuver classes (it was trained without "
        "diffusion.intent_conditioning): leave it at 1, 1, 1",
    )
