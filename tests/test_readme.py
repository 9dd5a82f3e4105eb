"""The README's code: its library section's Python blocks run, in order, in one namespace, as a
reader pastes them (on a tiny gridworld model standing in for the quickstart's), so that they
cannot rot."""

import os
import re

import numpy as np
import pytest

from conftest import ROOT
from wmjax.config import load_config
from wmjax.train.loop import train

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def python_blocks(section: str) -> list[str]:
  """The ```python blocks of the README's ``## section`` (up to the next ``## `` heading)."""
  text = (ROOT / "README.md").read_text()
  start = text.index(f"\n## {section}\n")
  end = text.find("\n## ", start + 1)
  return re.findall(r"```python\n(.*?)```", text[start:end if end >= 0 else None], re.S)


@pytest.fixture(scope="module")
def readers_directory(tmp_path_factory):
  """A directory with ``configs/`` and ``workdirs/gridworld``: a tiny gridworld model of the
  quickstart's recipe (1 context frame, 1-frame blocks) with 4 held-out episodes of 10 steps."""
  root = tmp_path_factory.mktemp("reader")
  overrides = {
      "data.data_dir": str(root / "data"), "data.gridworld.train_episodes": 8,
      "data.gridworld.test_episodes": 4, "data.gridworld.episode_length": 10,
      "model.hidden_size": 32, "model.depth": 2, "model.num_heads": 2, "batch_size": 8,
      "train.num_steps": 2, "train.checkpoint_every": 2, "train.eval_every": 0}
  config = load_config(str(ROOT / "configs" / "gridworld.py"),
                       [f"{k}={v!r}" for k, v in overrides.items()])
  train(config, str(root / "workdirs" / "gridworld"))
  os.symlink(ROOT / "configs", root / "configs")
  return root


def test_the_library_section_runs_as_written(readers_directory, monkeypatch):
  blocks = python_blocks("Using wmjax as a library")
  assert len(blocks) >= 5
  monkeypatch.chdir(readers_directory)
  namespace: dict = {}
  for number, block in enumerate(blocks):
    try:
      exec(compile(block, f"README.md, library block {number}", "exec"), namespace)
    except Exception as error:
      raise AssertionError(f"README library block {number} fails:\n{block}") from error
  # what the blocks say they make
  assert namespace["latents"].shape == (4, 10, 16, 16, 3)     # rollout of the held-out episodes
  assert namespace["env"].video().shape == (4, 9, 16, 16, 3)  # closed loop, 8 steps
  assert namespace["video"].shape == (2, 27, 32, 32, 16)      # the model from a config
  assert np.isfinite(float(namespace["loss"])) and np.isfinite(float(namespace["metrics"]["loss"]))
