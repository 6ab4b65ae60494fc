"""cvmdx_jax: cVMDx (uncertainty-aware diffusion for multimodal highway
trajectory prediction) in JAX/Flax."""

__version__ = "0.1.0"
