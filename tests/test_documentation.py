"""The code users copy: the Python blocks of the library page (docs/library.md) run, in order, in
one namespace, as a reader pastes them, and every script in examples/ runs, at tiny settings, on the
suite's tiny gridworld model (conftest.py) standing in for the quickstart's, so that none of it
can rot."""

import os
import re
import runpy

import numpy as np
import pytest

from conftest import ROOT, gridworld_overrides

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def python_blocks(page: str) -> list[str]:
  """The ```python blocks of the documentation page ``docs/PAGE``, in order."""
  return re.findall(r"```python\n(.*?)```", (ROOT / "docs" / page).read_text(), re.S)


@pytest.fixture(scope="module")
def readers_directory(trained_workdir, tmp_path_factory):
  """A directory with ``configs/`` and ``workdirs/gridworld``, as after the README quickstart:
  here the suite's tiny gridworld model (conftest.py; 2 held-out episodes of 12 steps)."""
  root = tmp_path_factory.mktemp("reader")
  os.symlink(ROOT / "configs", root / "configs")
  (root / "workdirs").mkdir()
  os.symlink(trained_workdir, root / "workdirs" / "gridworld")
  return root


def test_the_library_section_runs_as_written(readers_directory, monkeypatch):
  blocks = python_blocks("library.md")
  assert len(blocks) >= 5
  monkeypatch.chdir(readers_directory)
  namespace: dict = {}
  for number, block in enumerate(blocks):
    try:
      exec(compile(block, f"docs/library.md, block {number}", "exec"), namespace)
    except Exception as error:
      raise AssertionError(f"docs/library.md block {number} fails:\n{block}") from error
  # what the blocks say they make
  assert namespace["latents"].shape == (2, 12, 16, 16, 3)     # rollout of the held-out episodes
  assert namespace["env"].video().shape == (2, 9, 16, 16, 3)  # closed loop, 8 steps
  assert namespace["video"].shape == (2, 27, 32, 32, 16)      # the model from a config
  assert np.isfinite(float(namespace["loss"])) and np.isfinite(float(namespace["metrics"]["loss"]))


def run_example(name: str, *argv: str):
  """``examples/<name>.py``'s ``main(argv)`` (in this process: no second JAX start-up)."""
  return runpy.run_path(str(ROOT / "examples" / f"{name}.py"))["main"](list(argv))


def test_every_example_is_run_here():
  ran = set(re.findall(r'run_example\("(\w+)"', (ROOT / "tests" / "test_documentation.py")
                       .read_text()))
  assert ran == {p.stem for p in (ROOT / "examples").glob("*.py")}


def test_examples_rollout_and_closed_loop(readers_directory, tmp_path):
  workdir = str(readers_directory / "workdirs" / "gridworld")
  frames = np.random.default_rng(0).integers(0, 256, (2, 1, 16, 16, 3), np.uint8)
  np.save(tmp_path / "frames.npy", frames)
  np.save(tmp_path / "actions.npy", np.ones((2, 5, 4), np.float32))
  video = run_example("rollout_own_frames", workdir, "--frames", str(tmp_path / "frames.npy"),
                      "--actions", str(tmp_path / "actions.npy"), "--out",
                      str(tmp_path / "out.gif"))
  assert video.shape == (2, 6, 16, 16, 3) and (tmp_path / "out.png").exists()
  np.testing.assert_array_equal(video[:, 0], frames[:, 0])  # the context frame, unchanged
  video = run_example("closed_loop", workdir, "--frames", str(tmp_path / "frames.npy"),
                      "--steps", "3")
  assert video.shape == (2, 1 + 3 * 5, 16, 16, 3)  # 3 steps of the model's horizon, 5 frames


def test_example_evaluate_policy(readers_directory):
  result = run_example("evaluate_policy", str(readers_directory / "workdirs" / "gridworld"),
                       "--episodes", "3", "--steps", "2")
  assert {"pearson", "ranking_preserved"} <= set(result)


def test_example_improve_policy(readers_directory):
  result = run_example("improve_policy", str(readers_directory / "workdirs" / "gridworld"),
                       "--rounds", "1", "--rollouts", "8", "--clone_steps", "2",
                       "--fit_steps", "2")
  assert result["before"].shape == result["after"].shape == (64,)
  assert [r["round"] for r in result["history"]] == [0, 1]
  assert result["history"][1]["kept_episodes"] == 1  # the best 10 % of 8


def test_example_train_loop(data_dir, monkeypatch):
  monkeypatch.chdir(ROOT)
  losses = run_example("train_loop", "--steps", "3",
                       *(f"--config.{o}" for o in gridworld_overrides(data_dir)))
  assert len(losses) == 3 and np.isfinite(losses).all()


def test_example_shard_over_mesh(monkeypatch):
  monkeypatch.chdir(ROOT)
  video = run_example("shard_over_mesh", "--config", "configs/irasim.py:S", "--mesh", "1,-1,1",
                      "--config.model.depth=2", "--config.model.hidden_size=64",
                      "--config.model.num_heads=2", "--config.frame_shape=(8,8,4)",
                      "--config.sampling.num_steps=2")
  assert video.shape[0] == 8 and video.shape[2:] == (8, 8, 4)
