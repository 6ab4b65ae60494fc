"""Tests of the shared training infrastructure (loop, checkpoints, sharding)."""
