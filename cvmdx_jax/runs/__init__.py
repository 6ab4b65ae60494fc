"""Run directories: file layout and writers (`layout`), fingerprints (`fingerprints`),
saved tokens (`tokens`) and the reading of a trained run into its parts (`loaders`).
Import the module you need: this package imports none of them, so the trainers reach the
layout without the readers."""
