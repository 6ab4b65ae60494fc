"""Every typed config and its checks (frozen dataclasses, hashable, static under jit).

  fields    `ConfigFieldError`, the range rules, `to_dataclass` (config section -> dataclass)
  models    the networks: `EncoderConfig`, `QuantizerConfig`, `TokenizerConfig`,
            `UNetConfig`, `MultipleChoiceConfig`
  denoiser  `DenoiserConfig`: what a trained denoiser is (T, control scale, conditioning)
  sampling  `GuidanceConfig`, `HypothesisConfig`, `SamplingConfig`, `check_sampling` (a
            sampling config against a denoiser)
  train     the `train` sections of the trainers
  runs      the run configs (`TokenizerRunConfig`, `DiffusionRunConfig`, `DistillRunConfig`,
            `BaselineRunConfig`), built from configs/*.py by `from_config`

Nothing here imports model, training or inference code: the models import their configs
from here, so this package sits below every other one.
"""
