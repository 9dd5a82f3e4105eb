"""Generated datasets are written once, also when several jobs start together. (One whose task
is not imported fails naming config.task: tests/test_layering.py.)"""

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration

PREPARE = """
import sys
from wmjax.tasks.gridworld.dataset import GridworldConfig, prepare
print(prepare(sys.argv[1], GridworldConfig(image_size=8, square_size=2, episode_length=4,
                                           train_episodes=4, test_episodes=2, seed=7)))
"""


@pytest.mark.slow
def test_two_processes_preparing_one_dataset_both_succeed(tmp_path):
  jobs = [subprocess.Popen([sys.executable, "-c", PREPARE, str(tmp_path)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True) for _ in range(2)]
  results = [job.communicate(timeout=600) for job in jobs]
  for job, (out, err) in zip(jobs, results):
    assert job.returncode == 0, err[-2000:]
    assert "downloaded and prepared" not in out + err  # TFDS's line: nothing is downloaded
  # to a pipe, not a terminal: plain progress lines of the one that wrote it, no TFDS bars
  assert all("\r" not in out + err and "Generating splits" not in err for out, err in results)
  assert sum("gridworld train: 4/4 episodes" in out for out, _ in results) == 1
  paths = {out.strip().splitlines()[-1] for out, _ in results}
  assert len(paths) == 1
  (path,) = paths
  assert os.path.isfile(os.path.join(path, "dataset_info.json"))
  assert not [d for d in os.listdir(os.path.dirname(path)) if d.startswith("incomplete")]


def test_a_written_dataset_is_found_without_its_builder(tmp_path, monkeypatch):
  """Reading a generated dataset again builds no TFDS builder (which needs TensorFlow, absent
  on GPU images), and returns the directory the first prepare wrote."""
  from wmjax.tasks.gridworld import dataset

  config = dataset.GridworldConfig(image_size=8, square_size=2, episode_length=4,
                                   train_episodes=4, test_episodes=2, seed=7)
  written = dataset.prepare(str(tmp_path), config)

  def no_builder(*args, **kwargs):
    raise AssertionError("the builder was constructed for a dataset already written")

  monkeypatch.setattr(dataset.Gridworld, "__init__", no_builder)
  assert dataset.prepare(str(tmp_path), config) == written
  os.remove(os.path.join(written, "dataset_info.json"))  # unfinished: prepare builds again
  with pytest.raises(AssertionError, match="builder was constructed"):
    dataset.prepare(str(tmp_path), config)


def test_a_bad_split_of_a_generated_dataset_fails_before_generating_it(tmp_path, capsys):
  """`wmjax train` with a misspelt split on a machine where the gridworld is not yet generated:
  one line naming the splits, and nothing generated (nor printed) before it."""
  from conftest import ROOT, one_line_error
  data_dir = tmp_path / "data"
  one_line_error(capsys, ["train", "--config", str(ROOT / "configs" / "gridworld.py"),
                          "--workdir", str(tmp_path / "run"), f"--config.data.data_dir={data_dir!r}",
                          "--config.data.eval_split='tset'"],
                 r"config.data.eval_split='tset': the generated gridworld dataset has the splits "
                 r"\['train', 'test'\]")
  assert not data_dir.exists() and not (tmp_path / "run").exists()
