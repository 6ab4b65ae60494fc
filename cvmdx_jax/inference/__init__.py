"""The inference path: the trained-model bundles (`bundles`), sampling (`sampling`) and the
trained-model entry point (`predictor`)."""
