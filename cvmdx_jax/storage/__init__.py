"""Bytes on disk: atomic writes, checksums, orbax checkpoints, workdir locks."""
