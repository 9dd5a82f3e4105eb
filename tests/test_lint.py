"""ruff over the repository with pyproject.toml's rules (skipped where ruff is not installed;
``pip install -e .[test]`` brings it)."""

import pathlib
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _ruff() -> list[str] | None:
  if shutil.which("ruff"):
    return ["ruff"]
  try:
    import ruff  # noqa: F401  (the wheel ships the binary beside the module)
  except ImportError:
    return None
  return [sys.executable, "-m", "ruff"]


@pytest.mark.unit
def test_ruff_finds_nothing():
  ruff = _ruff()
  if ruff is None:
    pytest.skip("ruff is not installed (pip install -e .[test])")
  done = subprocess.run(ruff + ["check", "--no-cache", "--output-format", "concise", "."],
                        cwd=ROOT, capture_output=True, text=True, timeout=300)
  assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
