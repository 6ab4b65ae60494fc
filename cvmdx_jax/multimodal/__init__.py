"""Motion hypotheses: scaling, PCA and GMM/BIC over sampled trajectories, in JAX."""

from cvmdx_jax.multimodal.hypotheses import fit_hypotheses
from cvmdx_jax.multimodal.hypotheses import HypothesisConfig
from cvmdx_jax.multimodal.hypotheses import Hypotheses

__all__ = ["fit_hypotheses", "HypothesisConfig", "Hypotheses"]
