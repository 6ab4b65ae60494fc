"""What experiments/benchmark*.py share (and tests that need untrained models):

timing         first call and median of warm calls; one prediction, one training step
random_models  tokeniser, denoiser and `Predictor` of random weights; random scenarios
reference      the official-size timings in ../shared/reference_bench's schema, tables
"""
