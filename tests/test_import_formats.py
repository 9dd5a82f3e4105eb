"""Issue 37: `wmjax data import irasim | wpe` on small datasets written here in the IRASim and
WPE layouts (bytedance/IRASim, world-model-eval/world-model-eval): what lands in the RLDS, the
bad inputs (one error line naming the file, or a counted skip), and import -> inspect -> the
training command's data."""

import dataclasses
import json
import logging
import os
import re

import numpy as np
import pytest

from conftest import OWN_DATA_TINY, inspected_command, one_line_error
from wmjax import cli
from wmjax.config import load_config
from wmjax.data import oxe
from wmjax.data.rlds import decode_image
from wmjax.data.irasim import euler_to_matrix, matrix_to_euler, relative_actions
from wmjax.data.sources import ArrayRecordEpisodes, open_builder
from wmjax.data.videoio import read_video
from wmjax.eval.video import write_video
from wmjax.train.data import build_data, eval_windows

pytestmark = pytest.mark.integration

SIZE = 32
TEXTS = ("pick coke can", "open drawer", "move near", "close drawer")


def _frames(episode, length):
  t = np.arange(length)[:, None, None, None]
  y, x = np.mgrid[0:SIZE, 0:SIZE]
  base = np.stack([x * 7, y * 7, np.full_like(x, 50 * episode)], -1)[None]
  return ((base + 25 * t) % 256).astype(np.uint8)


def _states(episode, length):
  rng = np.random.default_rng(episode)
  state = np.concatenate([np.cumsum(rng.normal(0, 0.02, (length, 3)), 0),
                          rng.uniform(-3, 3, (length, 3)), rng.normal(size=(length, 1))], 1)
  return state, rng.uniform(0, 1, length)


def write_irasim(root, dataset, splits):
  """One IRASim dataset directory (``root/<dataset>``); ``splits``: split -> episode lengths
  (frames). RT-1 annotations as dataset_3D reads them, Language-Table's as dataset_2D does."""
  src = root / dataset
  for split, lengths in splits.items():
    os.makedirs(src / "annotation" / split)
    for e, n in enumerate(lengths):
      episode = f"{e:06d}" if dataset == "languagetable" else str(e)
      if dataset == "languagetable":
        video = f"videos/{split}/{episode}.mp4"
        annotation = {"actions": np.random.default_rng(e).normal(size=(n - 1, 2)).tolist(),
                      "video_path": video, "latent_video_path": f"latent_videos/{split}/{episode}.pt",
                      "episode_id": episode}
      else:
        video = f"videos/{split}/{episode}/rgb.mp4"
        state, gripper = _states(e, n)
        annotation = {"texts": [TEXTS[e % 4]], "state": state.tolist(),
                      "continuous_gripper_state": gripper.tolist(), "episode_id": episode,
                      "videos": [{"video_path": video}],
                      "latent_videos": [{"latent_video_path": f"latent_videos/{split}/{episode}/0.pt"}]}
      os.makedirs((src / video).parent, exist_ok=True)
      write_video(str(src / video), _frames(e, n), fps=4, scale=1)
      (src / "annotation" / split / f"{episode}.json").write_text(json.dumps(annotation))
  return src


def write_wpe(root, subsets):
  """download_data.py's layout: ``root/<subset>/<split>/NNNNNNNNN.mp4`` + ``.npz`` (``arr_0``
  float32 [T, 10]); ``subsets``: subset -> split -> episode lengths."""
  for subset, splits in subsets.items():
    for split, lengths in splits.items():
      os.makedirs(root / subset / split)
      for i, n in enumerate(lengths):
        base = root / subset / split / f"{i:09d}"
        write_video(f"{base}.mp4", _frames(i, n), fps=20, scale=1)
        np.savez(f"{base}.npz", np.random.default_rng(i).normal(size=(n, 10)).astype(np.float32))
  return root


def _import(capsys, *args):
  """Run `wmjax data import ...` in this process; its output directory."""
  capsys.readouterr()
  assert cli.main(["data", "import", *map(str, args)]) == 0
  return capsys.readouterr().out.strip().splitlines()[-1]


def _error(capsys, *args):
  """The one error line a failing `wmjax data import ...` writes (exit status 2; TFDS's progress
  bars may come before it) and no traceback."""
  capsys.readouterr()
  assert cli.main(["data", "import", *map(str, args)]) == 2
  err = capsys.readouterr().err
  line = err.strip().splitlines()[-1]
  assert "Traceback" not in err and line.startswith(f"wmjax data import {args[0]}: ")
  assert line.endswith("(--debug shows the traceback)")
  return line


def test_rotations_follow_irasims_convention():
  """R = Rz(yaw) Ry(pitch) Rx(roll), i.e. scipy's extrinsic 'xyz'; and back."""
  from scipy.spatial.transform import Rotation
  rpy = np.random.default_rng(0).uniform([-3, -1.5, -3], [3, 1.5, 3], (50, 3))
  np.testing.assert_allclose(euler_to_matrix(rpy), Rotation.from_euler("xyz", rpy).as_matrix(),
                             atol=1e-12)
  np.testing.assert_allclose(matrix_to_euler(euler_to_matrix(rpy)), rpy, atol=1e-9)


def test_irasim_rt1_import(tmp_path, capsys):
  from scipy.spatial.transform import Rotation
  src = write_irasim(tmp_path, "rt1", {"train": (5, 4), "val": (3,), "test": (6,)})
  out = _import(capsys, "irasim", src, tmp_path / "out")
  builder = open_builder(out)
  assert builder.info.name == "irasim_rt1" and set(builder.info.splits) == {"train", "val", "test"}
  assert builder.info.metadata["action_scale"] == [20.0] * 6 + [1.0]
  episodes = ArrayRecordEpisodes(out, "train")  # the built-in irasim_rt1 spec
  assert (episodes.spec.name, episodes.spec.action_dim, episodes.spec.gripper_dim) == (
      "irasim_rt1", 7, 6)
  states = ArrayRecordEpisodes(out, "train", dataclasses.replace(
      oxe.SPECS["irasim_rt1"][0], extra_keys=("observation/state", "observation/gripper_state")))
  assert episodes.lengths().tolist() == [5, 4]
  for e, n in enumerate((5, 4)):
    episode, extras = episodes.episode(e), states.episode(e).extras
    state, gripper = _states(e, n)
    # the motion in the previous end-effector frame, by scipy (IRASim's c_act_scaler is left to
    # the normalisation)
    previous = Rotation.from_euler("xyz", state[:-1, 3:6])
    current = Rotation.from_euler("xyz", state[1:, 3:6])
    expected = np.concatenate([previous.inv().apply(state[1:, :3] - state[:-1, :3]),
                               (previous.inv() * current).as_euler("xyz"),
                               gripper[1:, None]], 1)
    np.testing.assert_allclose(episode.actions[:-1], expected, atol=1e-4)
    np.testing.assert_array_equal(episode.actions[-1], np.zeros(7))
    assert episode.instruction == TEXTS[e]
    np.testing.assert_allclose(extras["state"], state, rtol=1e-6)
    np.testing.assert_allclose(extras["gripper_state"][:, 0], gripper, rtol=1e-6)
    assert int(episodes._record(e)["episode_metadata"]["episode_id"]) == e
    video = read_video(str(src / f"videos/train/{e}/rgb.mp4"))
    frames = np.stack([decode_image(b, None) for b in episode.images])
    np.testing.assert_array_equal(frames, video)  # PNG keeps the decoded video exactly
  np.testing.assert_allclose(relative_actions(*_states(0, 5)), episodes.episode(0).actions[:-1],
                             atol=1e-4)


def test_irasim_languagetable_import(tmp_path, capsys):
  """dataset_2D: T frames, the annotation's T-1 actions times 20, the dataset found by name."""
  src = write_irasim(tmp_path, "languagetable", {"test": (4, 6)})
  out = _import(capsys, "irasim", src, tmp_path / "out")
  episodes = ArrayRecordEpisodes(out, "test")
  assert episodes.spec.name == "irasim_languagetable" and episodes.spec.action_dim == 2
  assert episodes.lengths().tolist() == [4, 6]
  for e, n in enumerate((4, 6)):
    raw = np.random.default_rng(e).normal(size=(n - 1, 2))
    np.testing.assert_allclose(episodes.episode(e).actions[:-1], raw, rtol=1e-6)
    assert episodes.episode(e).instruction == ""


def test_wpe_import_pools_subsets_and_skips_like_wpe(tmp_path, capsys, caplog):
  root = write_wpe(tmp_path / "converted", {"rt_1": {"train": (4, 5), "test": (3,)},
                                            "bridge": {"train": (6,)}})
  os.remove(root / "rt_1" / "train" / "000000001.npz")  # WPE skips an mp4 without its npz
  (root / "bridge" / "train" / "000000000.npz").write_bytes(b"not an npz")  # and a broken npz
  write_video(str(root / "bridge" / "train" / "000000001.mp4"), _frames(1, 3), fps=20, scale=1)
  np.savez(root / "bridge" / "train" / "000000001.npz", np.ones((3, 10), np.float32))
  with caplog.at_level(logging.WARNING, logger="wmjax.data.wpe"):
    out = _import(capsys, "wpe", root, tmp_path / "out")
  assert "skipped 1 video(s) with no npz" in caplog.text
  assert "skipped 1 video(s) with npz that does not load" in caplog.text
  builder = open_builder(out)
  assert builder.info.metadata["subsets"] == {"train": {"bridge": 1, "rt_1": 1},
                                              "test": {"bridge": 0, "rt_1": 1}}
  episodes = ArrayRecordEpisodes(out, "train")  # the built-in wpe spec
  assert (episodes.spec.name, episodes.spec.action_dim, episodes.spec.gripper_dim) == ("wpe", 10, 6)
  assert episodes.lengths().tolist() == [3, 4]  # bridge first (name order), then rt_1
  np.testing.assert_array_equal(episodes.episode(0).actions, np.ones((3, 10)))
  np.testing.assert_array_equal(
      episodes.episode(1).actions,
      np.random.default_rng(0).normal(size=(4, 10)).astype(np.float32))
  # one subset chosen, or one subset's directory given
  only = _import(capsys, "wpe", root, tmp_path / "rt1", "--subsets", "rt_1")
  single = _import(capsys, "wpe", root / "rt_1", tmp_path / "rt1_dir")
  for path in (only, single):
    assert ArrayRecordEpisodes(path, "test").lengths().tolist() == [3]
    assert open_builder(path).info.metadata["subsets"]["train"] == {"rt_1": 1}


def test_inspect_on_a_raw_folder_names_the_import_command(tmp_path, capsys):
  """Issue 49: a LeRobot (recognised by its meta/info.json alone), IRASim or WPE folder given
  where a prepared dataset belongs: one line with the `wmjax data import` command for it."""
  lerobot = tmp_path / "lerobot"
  os.makedirs(lerobot / "meta")
  (lerobot / "meta" / "info.json").write_text("{}")
  wpe = write_wpe(tmp_path / "converted", {"rt_1": {"train": (3,)}})
  folders = {lerobot: ("lerobot", "LeRobot"), wpe: ("wpe", "WPE"), wpe / "rt_1": ("wpe", "WPE"),
             write_irasim(tmp_path, "rt1", {"test": (3,)}): ("irasim", "IRASim")}
  for path, (command, name) in folders.items():
    one_line_error(capsys, ["data", "inspect", str(path)],
                   rf"no TFDS dataset at '{re.escape(str(path))}' but a raw {name} dataset: "
                   rf"import it first with `wmjax data import {command} {re.escape(str(path))} "
                   rf"OUT_DIR`, then use OUT_DIR")
  one_line_error(capsys, ["data", "inspect", str(tmp_path / "rt1" / "annotation")],
                 r"\(expected dataset_info.json and features.json of a prepared dataset\)")


def test_an_annotation_without_actions_is_an_error_naming_it(tmp_path, capsys):
  src = write_irasim(tmp_path, "languagetable", {"test": (4, 4)})
  path = src / "annotation" / "test" / "000001.json"
  annotation = json.loads(path.read_text())
  del annotation["actions"]
  path.write_text(json.dumps(annotation))
  line = _error(capsys, "irasim", src, tmp_path / "out")
  assert f"{path}: the annotation has no 'actions'" in line
  assert not os.path.exists(tmp_path / "out")


def test_an_annotation_that_is_not_json_is_skipped_and_counted(tmp_path, capsys, caplog):
  src = write_irasim(tmp_path, "rt1", {"train": (4, 4)})
  (src / "annotation" / "train" / "1.json").write_text("{not json")
  with caplog.at_level(logging.WARNING, logger="wmjax.data.irasim"):
    out = _import(capsys, "irasim", src, tmp_path / "out")
  assert "skipped 1 annotation(s) that are not valid JSON" in caplog.text
  assert ArrayRecordEpisodes(out, "train").lengths().tolist() == [4]


def test_irasim_needs_a_known_dataset_directory(tmp_path, capsys):
  root = tmp_path / "opensource_robotdata"
  write_irasim(root, "bridge", {"train": (3,)})
  line = _error(capsys, "irasim", root, tmp_path / "out")
  assert "it holds the datasets ['bridge']: import one" in line


def test_mixed_action_widths_are_an_error_naming_the_file(tmp_path, capsys):
  root = write_wpe(tmp_path / "converted", {"rt_1": {"train": (3, 3)}})
  npz = root / "rt_1" / "train" / "000000001.npz"
  np.savez(npz, np.zeros((3, 7), np.float32))
  line = _error(capsys, "wpe", root, tmp_path / "out")
  assert f"{npz}: 7-dim actions, but the first episode's are 10-dim" in line


def test_an_unreadable_video_is_an_error_naming_it(tmp_path, capsys):
  root = write_wpe(tmp_path / "converted", {"rt_1": {"train": (3, 3)}})
  video = root / "rt_1" / "train" / "000000001.mp4"
  video.write_bytes(b"not a video")
  line = _error(capsys, "wpe", root, tmp_path / "out")
  assert f"{video} is not a readable video" in line
  assert not os.path.exists(tmp_path / "out")


def test_a_video_longer_than_its_actions_is_cut_with_a_warning_counting_it(tmp_path, capsys,
                                                                           caplog):
  """Issue 49: 5 actions beside a 32-frame mp4 import 5 steps and say that 27 frames are left
  out, naming the video."""
  root = write_wpe(tmp_path / "converted", {"rt_1": {"train": (32, 4)}})
  np.savez(root / "rt_1" / "train" / "000000000.npz", np.zeros((5, 10), np.float32))
  with caplog.at_level(logging.WARNING, logger="wmjax.data.writer"):
    out = _import(capsys, "wpe", root, tmp_path / "out")
  video = root / "rt_1" / "train" / "000000000.mp4"
  assert [r.getMessage() for r in caplog.records if r.name == "wmjax.data.writer"] == [
      f"{video} has 32 frames but its episode 5 actions (one per frame): imported 5 steps, 27 "
      f"frames left out"]
  assert ArrayRecordEpisodes(out, "train").lengths().tolist() == [5, 4]


def test_a_video_shorter_than_its_actions_is_an_error_naming_it(tmp_path, capsys):
  root = write_wpe(tmp_path / "converted", {"rt_1": {"train": (3,)}})
  np.savez(root / "rt_1" / "train" / "000000000.npz", np.zeros((5, 10), np.float32))
  line = _error(capsys, "wpe", root, tmp_path / "out")
  assert f"{root / 'rt_1' / 'train' / '000000000.mp4'}: frames [0, 5) asked for" in line


@pytest.mark.parametrize("fmt", ["irasim", "wpe"])
def test_the_command_inspect_prints_reads_the_imported_data(tmp_path, capsys, fmt):
  """What a user of IRASim's or WPE's data runs: import, inspect, and the training command inspect
  prints (tiny widths): its config takes the data's action width and reads training windows, and
  the evaluation windows of IRASim's evaluation split (test) / WPE's test split. That such a
  command then trains and evaluates: test_data_specs.py::test_own_lerobot_data_from_import_to_evaluation."""
  if fmt == "irasim":
    src = write_irasim(tmp_path, "rt1", {"train": (5, 5, 4), "test": (5,)})
  else:
    src = write_wpe(tmp_path / "converted", {"rt_1": {"train": (5, 5, 4), "test": (5,)}})
  out = _import(capsys, fmt, src, tmp_path / "data")
  printed, command = inspected_command(capsys, out, str(tmp_path / "run"))
  name, dim = ("irasim_rt1", 7) if fmt == "irasim" else ("wpe", 10)
  assert f"this is the built-in {name!r} spec ({dim}-dim actions, gripper dimension 6" in printed
  assert f"--config.model.action_dim={dim}" in command
  tiny = {**OWN_DATA_TINY, "data.train_split": "train", "data.eval_split": "test"}
  config = load_config(command[command.index("--config") + 1],
                       [a.removeprefix("--config.") for a in command if a.startswith("--config.")]
                       + [f"{k}={v!r}" for k, v in tiny.items()])
  data = build_data(config)  # what `wmjax train` checks against the model before compiling
  (member,) = data.members
  assert (member.spec.name, member.spec.action_dim) == (name, dim)
  frames = config.data.frames
  assert len(member.train) == sum(n - frames + 1 for n in (5, 5, 4))  # every window, stride 1
  assert member.train[0]["frames"].shape == (frames, 16, 16, 3)
  assert member.train[0]["actions"].shape == (frames - 1, dim)
  assert [int(e) for e in member.eval.episodes.lengths()] == [5]  # the test split
  windows = eval_windows(data, config)
  assert windows["frames"].shape[1:] == (frames, 16, 16, 3)
  assert np.isfinite(windows["actions"]).all() and windows["actions"].shape[2] == dim


@pytest.mark.slow
def test_the_printed_command_runs_as_printed_on_one_episode_from_another_directory(
    tmp_path, capsys, monkeypatch):
  """IRASim's Language-Table example: one ``test`` split of one episode. ``inspect`` says that
  training and evaluation share it, and its command runs as printed (tiny widths added) from a
  directory that is not the checkout, then ``evaluate`` reads the same split."""
  from wmjax import cli
  src = write_irasim(tmp_path, "languagetable", {"test": (6,)})
  out = _import(capsys, "irasim", src, tmp_path / "data")
  elsewhere = tmp_path / "elsewhere"
  elsewhere.mkdir()
  monkeypatch.chdir(elsewhere)
  printed, command = inspected_command(capsys, out, "run")
  assert "one episode in all: training and evaluation share it" in printed
  assert "--config.data.train_split=test" in command and "--config.data.eval_split=test" in command
  assert cli.main(command[1:] + [f"--config.{k}={v!r}" for k, v in OWN_DATA_TINY.items()]) == 0
  assert cli.main(["evaluate", "--workdir", "run", "--protocols", "long", "--videos", "0"]) == 0
  assert (elsewhere / "run" / "eval" / "test-step1" / "metrics.json").is_file()
