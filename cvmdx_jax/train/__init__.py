"""Training: the shared loop and the per-model steps."""
