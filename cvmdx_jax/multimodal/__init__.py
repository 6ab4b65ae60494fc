"""Motion hypotheses over sampled trajectories, in JAX: scaling, PCA and GMM/BIC (the
paper) or k-means at a fixed K (`HypothesisConfig.method`)."""

from cvmdx_jax.multimodal.hypotheses import Hypotheses, fit_hypotheses

__all__ = ["fit_hypotheses", "Hypotheses"]
