"""Atomic file writes: write to a hidden temporary name beside the target, then rename,
so a reader never sees a half-written file and an existing one survives a crash."""

import json
import os
from pathlib import Path


def write_bytes(path, data: bytes) -> None:
  path = Path(path)
  tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
  tmp.write_bytes(data)
  os.replace(tmp, path)


def write_text(path, text: str) -> None:
  write_bytes(path, text.encode())


def write_json(path, value, **kwargs) -> None:
  write_text(path, json.dumps(value, **{"indent": 2, **kwargs}) + "\n")
