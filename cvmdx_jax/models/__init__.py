"""Neural network modules (Flax NNX), executed functionally."""
