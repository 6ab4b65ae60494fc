"""The inference path: sampling (`sampling`) and the trained-model entry point (`predictor`)."""
