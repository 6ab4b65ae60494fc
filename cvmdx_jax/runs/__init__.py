"""Run directories: their configs (`config`), file layout and writers (`layout`),
fingerprints (`fingerprints`), saved tokens (`tokens`) and the inference loaders
(`loaders`). Import the module you need: this package imports none of them, so the
trainers reach the layout without the inference path."""
