"""Issue 18: dataset specs as config, camera choice, per-split statistics, aspect-preserving
resizing, one too-short error on both read paths, `wmjax data inspect`, LeRobot import."""

import io
import json
import logging
import os
import shutil
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image
from tensorflow_datasets.core import file_adapters

import oxe_fixtures
from conftest import OWN_DATA_TINY, ROOT, inspected_command, one_line_error
from wmjax.data import oxe
from wmjax.data.convert import convert_to_array_record
from wmjax.data.lerobot import import_lerobot
from wmjax.data.pipeline import WindowSource
from wmjax.data.rlds import stream_windows
from wmjax.data.sources import (ArrayRecordEpisodes, action_stats, open_builder, read_episodes,
                                tfrecord_episodes)
from wmjax.data import videoio
from wmjax.data.videoio import read_video
from wmjax.eval.video import write_video
from wmjax.tasks.gridworld import dataset as gridworld

pytestmark = pytest.mark.integration


def _cli(*args):
  return subprocess.run([sys.executable, "-m", "wmjax.cli", *args], capture_output=True,
                        text=True, check=True).stdout


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
  """Bridge in the current layout, episode 0 without camera 3: (TFRecord dir, ArrayRecord dir)."""
  root = tmp_path_factory.mktemp("bridge")
  tfrecord = oxe_fixtures.build("bridge_dataset", str(root / "tfrecord"), absent_cameras={0: (3,)})
  return tfrecord, str(convert_to_array_record(tfrecord, root / "array_record"))


@pytest.fixture(scope="module")
def fractal(tmp_path_factory):
  root = tmp_path_factory.mktemp("fractal")
  tfrecord = oxe_fixtures.build("fractal20220817_data", str(root / "tfrecord"))
  return tfrecord, str(convert_to_array_record(tfrecord, root / "array_record"))


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
  config = gridworld.GridworldConfig(train_episodes=6, test_episodes=3, episode_length=8)
  return gridworld.prepare(str(tmp_path_factory.mktemp("grid")), config)


@pytest.mark.slow
def test_statistics_are_per_split(grid):
  """Failure 1: the test split's statistics were the train split's; train[:2] counted every
  train episode."""
  train = json.loads(_cli("data", "stats", grid))
  test = json.loads(_cli("data", "stats", grid, "--split", "test"))
  assert (train["count"], test["count"]) == (6 * 7, 3 * 7)  # the last step of each is left out
  assert train["split"] == "train" and test["split"] == "test" and train["mean"] != test["mean"]
  first_two = action_stats(grid, "train[:2]")
  actions = np.concatenate([e.actions[:-1] for e in read_episodes(grid, "train[:2]")])
  assert first_two.count == 2 * 7 == len(actions)
  np.testing.assert_allclose(first_two.mean, actions.mean(0), rtol=1e-5)
  assert action_stats(grid, "train").count == 6 * 7  # still its own after train[:2]


def test_camera_choice_skips_episodes_without_it(bridge, caplog):
  """Failure 2: data.image_key was ignored, and a camera an episode lacks gave black frames."""
  tfrecord_dir, array_record_dir = bridge
  specs = oxe.specs_from_config({"dataset": "bridge_dataset", "image_key": "observation/image_3"})
  with caplog.at_level(logging.WARNING):
    episodes = ArrayRecordEpisodes(array_record_dir, "train", specs)
    source = WindowSource(episodes, 4, 2, None)
  assert episodes.spec.image_keys == ("observation/image_3",)
  assert episodes.spec.image_flags == ("episode_metadata/has_image_3",)
  assert "skipped 1 of 3 episodes without the camera" in caplog.text
  assert episodes.lengths().tolist() == [0, 3, 7]
  assert {int(e) for e, _ in source.index} == {2}
  window = source[0]
  assert window["frames"].max() > 0  # never the black frames episode 0 holds for camera 3
  def distance(camera):  # to camera's picture (JPEG is lossy)
    raw = oxe_fixtures._smooth_image((256, 256, 3), 100 * 2 + 0 + 7 * camera)
    return np.abs(window["frames"][0].astype(int) - raw).mean()
  assert distance(3) < 3 < distance(0)
  streamed = list(stream_windows(tfrecord_episodes(tfrecord_dir, "train", specs), 4, 2, None))
  assert len(streamed) == len(source) == 2
  # both paths number an episode by its place in the split, the skipped episode 0 counted
  assert [int(w["episode"]) for w in streamed] == [int(source[i]["episode"]) for i in range(2)]
  assert [int(w["episode"]) for w in streamed] == [2, 2]
  np.testing.assert_array_equal(streamed[0]["frames"], window["frames"])
  # camera 0 exists everywhere: nothing is skipped
  assert ArrayRecordEpisodes(array_record_dir, "train", "bridge_dataset").lengths().tolist() == [5, 3, 7]
  strict = oxe.specs_from_config({"dataset": "bridge_dataset", "image_key": "observation/image_3",
                                  "missing_image": "error"})
  with pytest.raises(ValueError, match=r"episode 0 lacks the camera.*has_image_3"):
    ArrayRecordEpisodes(array_record_dir, "train", strict).lengths()
  with pytest.raises(ValueError, match=r"episode 0 lacks the camera"):
    list(tfrecord_episodes(tfrecord_dir, "train", strict))
  with pytest.raises(ValueError, match="observation/image_9"):
    ArrayRecordEpisodes(array_record_dir, "train", oxe.specs_from_config(
        {"dataset": "bridge_dataset", "image_key": "observation/image_9"}))


def test_several_views_and_fallbacks(bridge):
  _, array_record_dir = bridge
  specs = oxe.specs_from_config({"dataset": "bridge_dataset",
                                 "image_key": ("observation/image_1", "observation/wrist|observation/image_2")})
  episodes = ArrayRecordEpisodes(array_record_dir, "train", specs)
  assert episodes.spec.image_keys == ("observation/image_1", "observation/image_2")
  frames = WindowSource(episodes, 4, 2, (64, 128))[0]["frames"]
  assert frames.shape == (4, 64, 128, 3)
  left = WindowSource(ArrayRecordEpisodes(array_record_dir, "train", oxe.specs_from_config(
      {"dataset": "bridge_dataset", "image_key": "observation/image_1"})), 4, 2, (64, 64))[0]
  np.testing.assert_array_equal(frames[:, :, :64], left["frames"])


def test_tfrecord_episodes_says_what_it_reads(bridge):
  """Failure 3: tfrecord_episodes claimed to read ArrayRecord and raised NotImplementedError."""
  tfrecord_dir, array_record_dir = bridge
  with pytest.raises(ValueError, match="tf.data reads TFRecord only: read it with ArrayRecordEpisodes"):
    next(tfrecord_episodes(array_record_dir, "train"))
  a = [e.actions for e in read_episodes(array_record_dir, "train")]
  b = [e.actions for e in read_episodes(tfrecord_dir, "train")]
  assert len(a) == len(b) == 3
  for x, y in zip(a, b):
    np.testing.assert_array_equal(x, y)


def test_too_short_episodes_give_the_same_error_on_both_paths(bridge):
  """Failure 4: grain raised, tf.data yielded 0 windows silently."""
  tfrecord_dir, array_record_dir = bridge
  with pytest.raises(ValueError) as grain_error:
    WindowSource(ArrayRecordEpisodes(array_record_dir, "train"), 8, 1, None)
  with pytest.raises(ValueError) as tf_error:
    list(stream_windows(tfrecord_episodes(tfrecord_dir, "train"), 8, 1, None,
                        where=f"{array_record_dir} [train]"))
  assert str(grain_error.value) == str(tf_error.value)
  assert "no episode of at least 8 steps (3 episodes)" in str(tf_error.value)


@pytest.mark.parametrize("resize", ["crop", "pad"])
def test_resizing_keeps_the_aspect_ratio(bridge, resize):
  """Failure 5: Bridge's 256x256 frames were stretched to 256x320."""
  _, array_record_dir = bridge
  specs = oxe.specs_from_config({"dataset": "bridge_dataset", "resize": resize})
  episodes = ArrayRecordEpisodes(array_record_dir, "train", specs)
  assert episodes.spec.resolution == (256, 320)
  frames = WindowSource(episodes, 4, 2, episodes.spec.resolution)[0]["frames"]
  assert frames.shape == (4, 256, 320, 3)
  original = Image.open(io.BytesIO(episodes.episode(0).images[0])).convert("RGB")
  if resize == "pad":  # unscaled in the middle, black bars of 32 px on each side
    assert (frames[0, :, :32] == 0).all() and (frames[0, :, -32:] == 0).all()
    np.testing.assert_array_equal(frames[0, :, 32:-32], np.asarray(original))
  else:  # the central 256x205 rows, scaled by 1.25 both ways
    expected = original.resize((320, 256), Image.BILINEAR, box=(0, 25, 256, 230))
    np.testing.assert_array_equal(frames[0], np.asarray(expected))
    stretched = np.asarray(original.resize((320, 256), Image.BILINEAR))
    assert np.abs(frames[0].astype(int) - stretched).mean() > 2


def test_a_spec_in_config_reads_like_the_built_in_one(fractal):
  """An RLDS dataset read from a config spec alone: same windows as the built-in spec; action
  transforms and frame subsampling."""
  _, array_record_dir = fractal
  keys = ("action/world_vector", "action/rotation_delta", "action/gripper_closedness_action")
  config = {"dataset": "my_robot", "spec": dict(
      image_keys=("observation/image",), instruction_key="observation/natural_language_instruction",
      action_keys=keys, gripper_dim=6)}
  built_in = WindowSource(ArrayRecordEpisodes(array_record_dir, "train"), 4, 2, (32, 40))
  mine_episodes = ArrayRecordEpisodes(array_record_dir, "train", oxe.specs_from_config(config))
  mine = WindowSource(mine_episodes, 4, 2, (32, 40))
  assert mine_episodes.spec.name == "my_robot" and mine_episodes.spec.action_dim == 7
  for k in range(len(built_in)):
    for key in ("frames", "actions", "instruction"):
      np.testing.assert_array_equal(built_in[k][key], mine[k][key])
  raw = ArrayRecordEpisodes(array_record_dir, "train").episode(2).actions
  inverted = ArrayRecordEpisodes(array_record_dir, "train", oxe.specs_from_config(
      {**config, "spec": dict(config["spec"], action_transforms=("", "negate", "invert"))}))
  np.testing.assert_allclose(inverted.episode(2).actions,
                             np.concatenate([raw[:, :3], -raw[:, 3:6], 1 - raw[:, 6:]], 1))
  halved = ArrayRecordEpisodes(array_record_dir, "train", oxe.specs_from_config(
      {**config, "frame_step": 2}))
  assert halved.lengths().tolist() == [3, 2, 4]
  sub = halved.episode(2)  # steps 0, 2, 4, 6 of 7
  np.testing.assert_allclose(sub.actions[1, :6], raw[2:4, :6].sum(0), rtol=1e-6)
  assert sub.actions[1, 6] == raw[3, 6] and sub.actions[3, 6] == raw[6, 6]
  assert sub.images == ArrayRecordEpisodes(array_record_dir, "train").episode(2).images[::2]
  assert halved.episode(2, 1, 3).images == sub.images[1:3]
  with pytest.raises(ValueError, match="unknown action_transforms"):
    oxe.specs_from_config({**config, "spec": dict(config["spec"], action_transforms=("", "", "x"))})
  with pytest.raises(ValueError, match="no config.data.spec"):
    oxe.specs_from_config({"dataset": "my_robot"})
  # issue 49: the spec's default instruction key is not fractal's: the error names the field,
  # what the dataset has instead and the config key, not every step key
  without = {"dataset": "my_robot", "spec": dict(config["spec"], instruction_key="wrong")}
  with pytest.raises(ValueError) as error:
    ArrayRecordEpisodes(array_record_dir, "train", oxe.specs_from_config(without))
  assert str(error.value) == (
      "my_robot: the dataset's features match no known layout: spec.instruction_key 'wrong' not "
      "among the step keys (instructions there: ['observation/natural_language_instruction']); "
      "set config.data.spec.instruction_key ('' for none)")
  # a spec field set on a built-in dataset applies to its spec (no override silently ignored)
  changed = oxe.specs_from_config({"dataset": "bridge", "spec": oxe.spec_config(
      action_keys=(), instruction_key="WRONG", image_keys=["observation/image_1"])})
  assert [(s.layout, s.instruction_key, s.image_keys) for s in changed] == [
      ("oxe", "WRONG", ("observation/image_1",)), ("bridge_v2", "WRONG", ("observation/image_1",))]
  assert oxe.specs_from_config({"dataset": "bridge", "spec": oxe.spec_config(action_keys=())}) == (
      oxe.SPECS["bridge"])


def test_inspect_prints_features_and_a_spec_that_reads(fractal):
  _, array_record_dir = fractal
  out = _cli("data", "inspect", array_record_dir)
  assert "observation/natural_language_instruction" in out and "Image[256, 320, 3] uint8" in out
  assert "train (3 episodes)" in out
  # the built-in spec of the same dataset is named, not a guess that differs from it
  assert ("this is the built-in 'fractal20220817_data' spec (7-dim actions, gripper dimension 6"
          in out and f"--config.data.builder_dir={array_record_dir} --config.data.dataset="
          "fractal20220817_data --config.model.action_dim=7" in out)
  assert "suggested spec" not in out
  # issue 49: the keys the spec reads, and two decoded instructions per split
  assert ("reads: image observation/image; instruction observation/natural_language_instruction; "
          "actions action/world_vector + action/rotation_delta + "
          "action/gripper_closedness_action; state none\ninstructions (first two episodes):\n"
          "  train: 'pick up the red block', ''\n") in out
  from wmjax.data.describe import suggest_spec
  spec = suggest_spec("fractal", open_builder(array_record_dir).info.features)
  assert spec.action_keys == ("action/base_displacement_vector",  # name order, gripper last
                              "action/base_displacement_vertical_rotation", "action/rotation_delta",
                              "action/world_vector", "action/gripper_closedness_action")
  assert (spec.action_dim, spec.gripper_dim) == (10, 9)  # base 2 + 1, rotation 3, world 3, gripper
  assert spec.instruction_key == "observation/natural_language_instruction"
  episodes = ArrayRecordEpisodes(array_record_dir, "train", spec)
  assert episodes.episode(0).instruction == oxe_fixtures.INSTRUCTIONS[0]


def test_inspect_decodes_instructions_from_tfrecord_too(fractal, capsys):
  from wmjax import cli
  assert cli.main(["data", "inspect", fractal[0]]) == 0
  assert "instructions (first two episodes):\n  train: 'pick up the red block', ''\n" in (
      capsys.readouterr().out)


def test_inspect_on_tfrecord_prints_the_convert_command_before_the_one_that_trains(
    fractal, tmp_path, capsys):
  """Training reads ArrayRecord: on a TFRecord dataset inspect's last two commands are the
  conversion and the training run on its output, and both run as printed."""
  import shlex
  tfrecord = fractal[0]
  printed, command = inspected_command(capsys, tfrecord, str(tmp_path / "run"))
  lines = printed.splitlines()
  (at,) = [i for i, line in enumerate(lines) if line.strip().startswith("wmjax data convert")]
  convert = shlex.split(lines[at])
  assert convert[:3] == ["wmjax", "data", "convert"] and convert[3] == tfrecord
  assert at < len(lines) - 1 and f"--config.data.builder_dir={convert[4]}" in command
  from wmjax import cli
  from wmjax.config import load_config
  from wmjax.train.data import build_data
  assert cli.main(convert[1:]) == 0
  config = load_config(command[command.index("--config") + 1],
                       [a.removeprefix("--config.") for a in command if a.startswith("--config.")]
                       + [f"{k}={v!r}" for k, v in OWN_DATA_TINY.items()])
  assert len(build_data(config).members[0].train) > 0


def test_the_printed_command_follows_the_splits_the_data_has():
  """A dataset's own test split is held out; a dataset of one split other than train is carved
  into 90 % / 10 %; train alone keeps configs/rlds.py's ``train[:90%]`` / ``train[90%:]``; under
  10 episodes the last one is held out, and one episode (IRASim's Language-Table example: one
  ``test`` split of one episode) serves both, with a note saying so."""
  from wmjax.config import load_config
  from wmjax.data.describe import split_overrides
  assert split_overrides({"train": 9, "test": 2}) == (
      "--config.data.train_split=train --config.data.eval_split=test", "")
  only_test, note = split_overrides({"train": 0, "test": 18})
  assert only_test == ("--config.data.train_split='test[:90%]' "
                       "--config.data.eval_split='test[90%:]'") and not note
  assert split_overrides({"train": 15}) == split_overrides({"train": 15, "val": 0}) == ("", "")
  assert split_overrides({"train": 5}) == (
      "--config.data.train_split='train[:-1]' --config.data.eval_split='train[-1:]'",
      "5 episodes: the last one is held out for evaluation")
  one, note = split_overrides({"test": 1})
  assert one == "--config.data.train_split=test --config.data.eval_split=test"
  assert note.startswith("one episode in all: training and evaluation share it")
  rlds = load_config(str(ROOT / "configs" / "rlds.py"))
  assert (rlds.data.train_split, rlds.data.eval_split) == ("train[:90%]", "train[90%:]")
  overrides = [a.replace("'", "").removeprefix("--config.") for a in only_test.split()]
  config = load_config(str(ROOT / "configs" / "rlds.py"), overrides)  # as the shell passes them
  assert (config.data.train_split, config.data.eval_split) == ("test[:90%]", "test[90%:]")


def test_inspect_recognises_a_string_tensor_instruction():
  """The published layouts declare instructions as ``Tensor[] string``, not ``Text``."""
  import tensorflow_datasets as tfds
  from wmjax.data.describe import builtin_spec, suggest_spec
  F = tfds.features
  features = F.FeaturesDict({"steps": F.Dataset({
      "observation": {"rgb": F.Image(shape=(8, 8, 3)),
                      "natural_language_instruction": F.Tensor(shape=(), dtype=np.str_)},
      "action": F.Tensor(shape=(3,), dtype=np.float32)})})
  spec = suggest_spec("mine", features)
  assert (spec.instruction_key, spec.instruction_encoding) == (
      "observation/natural_language_instruction", "text")
  assert spec.image_keys == ("observation/rgb",) and spec.action_dim == 3
  assert builtin_spec("mine", features) is None  # no built-in layout has observation/rgb


def test_inspect_says_the_robot_state_is_not_read():
  """The reads line names the dataset's per-step robot state, which no spec role reads (the
  model is conditioned on actions) unless the spec carries it as an extra."""
  import tensorflow_datasets as tfds
  from wmjax.data.describe import _keys_read, state_keys
  F = tfds.features
  features = F.FeaturesDict({"steps": F.Dataset({
      "observation": {"image": F.Image(shape=(8, 8, 3)), "state": F.Tensor(shape=(7,),
                                                                           dtype=np.float32),
                      "gripper_state": F.Tensor(shape=(1,), dtype=np.float32),
                      "state_image": F.Image(shape=(8, 8, 3)), "statement": F.Text()},
      "action": F.Tensor(shape=(3,), dtype=np.float32)})})
  leaves = oxe.feature_leaves(features)
  assert state_keys(leaves) == ["observation/gripper_state", "observation/state"]
  spec = oxe.DatasetSpec("mine", action_dim=3)
  assert _keys_read(spec, leaves).endswith(
      "; state observation/gripper_state, observation/state, not read (the model is conditioned "
      "on actions; spec.extra_keys carries it into windows)")
  carried = oxe.DatasetSpec("mine", action_dim=3, extra_keys=("observation/state",))
  assert _keys_read(carried, leaves).endswith(
      "; extra observation/state; state observation/gripper_state, not read (the model is "
      "conditioned on actions; spec.extra_keys carries it into windows)")
  carried = oxe.DatasetSpec("mine", action_dim=3, extra_keys=tuple(state_keys(leaves)))
  assert _keys_read(carried, leaves).endswith("; state as extra")
  # RT-1's and Language-Table's robot state (issue 84.6)
  vector = F.Tensor(shape=(7,), dtype=np.float32)
  open_x = oxe.feature_leaves(F.FeaturesDict({"steps": F.Dataset({"observation": {
      "base_pose_tool_reached": vector, "gripper_closed": F.Tensor(shape=(1,), dtype=np.float32),
      "gripper_closedness_commanded": vector, "effector_translation": vector,
      "effector_target_translation": vector, "square_positions": vector}})}))
  assert state_keys(open_x) == [f"observation/{k}" for k in (
      "base_pose_tool_reached", "effector_target_translation", "effector_translation",
      "gripper_closed")]
  assert _keys_read(spec, {"observation/image": features["steps"]["observation"]["image"]}
                    ).endswith("; state none")


def test_the_documented_inspect_example_is_what_inspect_prints(tmp_path):
  """docs/data.md's `wmjax data inspect` output of a small gridworld, at the page's path: every
  line of it is printed, in order (its "..." stands for the lines it leaves out)."""
  from wmjax.data.describe import describe
  page = (ROOT / "docs" / "data.md").read_text()
  example = page.split("$ wmjax data inspect ", 1)[1].split("```", 1)[0].splitlines()[1:]
  builder_dir = gridworld.prepare(str(tmp_path), gridworld.GridworldConfig(
      train_episodes=8, test_episodes=2, episode_length=8))
  printed = describe(open_builder(builder_dir)).replace(str(tmp_path), "/root/tensorflow_datasets")
  printed = printed.replace(str(ROOT), "~/wmjax").splitlines()  # the checkout, for the page
  remaining = iter(printed)
  for line in (line for line in example if line.strip() != "..."):
    assert line in remaining, f"docs/data.md line not printed (in this order): {line!r}"


def _damaged_copy(builder_dir, destination, damage):
  """A copy of a one-shard builder directory whose shard ``damage(path)`` rewrites; its
  dataset_info.json still counts 3 episodes."""
  shutil.copytree(builder_dir, destination)
  (shard,) = destination.glob("*-train.*-00000-of-00001")
  damage(shard)
  return shard


def _emptied(shard):
  shard.write_bytes(b"")


def _cut_in_half(shard):
  shard.write_bytes(shard.read_bytes()[:shard.stat().st_size // 2])


def _without_records(shard):  # what converting an empty TFRecord shard used to write
  shard.unlink()
  file_adapters.ArrayRecordFileAdapter.write_examples(shard, iter(()))


def test_damaged_shards_are_refused_before_anything_is_written(fractal, tmp_path, capsys):
  """Issue 49: an empty TFRecord shard, and an ArrayRecord shard that is empty, cut short or of no
  records, beside a dataset_info.json that counts 3 episodes: inspect, convert and train exit 2
  naming the shard; convert writes no output and train leaves no workdir."""
  tfrecord_dir, array_record_dir = fractal
  shard = _damaged_copy(tfrecord_dir, tmp_path / "tfrecord", _emptied)
  empty = rf"{shard.name} is empty \(0 bytes\), but dataset_info.json counts 3 episodes in it"
  one_line_error(capsys, ["data", "inspect", str(shard.parent)], empty)
  one_line_error(capsys, ["data", "convert", str(shard.parent), str(tmp_path / "out")], empty)
  assert sorted(os.listdir(tmp_path)) == ["tfrecord"]
  # cut in half: its size looks right, reading it fails: one line, and no directory left behind
  shard = _damaged_copy(tfrecord_dir, tmp_path / "cut", _cut_in_half)
  cut = r"the data is damaged: a TFRecord shard is cut short or corrupted"
  one_line_error(capsys, ["data", "inspect", str(shard.parent)], cut)
  one_line_error(capsys, ["data", "convert", str(shard.parent), str(tmp_path / "new" / "out")],
                 "truncated TFRecord record")
  assert sorted(os.listdir(tmp_path)) == ["cut", "tfrecord"]
  for damage, problem in ((_emptied, r"is empty \(0 bytes\)"),
                          (_cut_in_half, r"is not a readable ArrayRecord file"),
                          (_without_records, "holds 0 episodes")):
    shard = _damaged_copy(array_record_dir, tmp_path / damage.__name__, damage)
    message = rf"{shard.name} {problem}.*, but dataset_info.json counts 3 episodes in it"
    one_line_error(capsys, ["data", "inspect", str(shard.parent)], message)
    workdir = tmp_path / f"run{damage.__name__}"
    one_line_error(capsys, ["train", "--config", os.path.join(ROOT, "configs", "rlds.py"),
                            "--workdir", str(workdir), f"--config.data.builder_dir={shard.parent}",
                            "--config.data.dataset='fractal20220817_data'",
                            "--config.model.action_dim=7"], message)
    assert not workdir.exists()


# ----------------------------------------------------------------------------- LeRobot

FPS, SIZE, LENGTHS = 10, 16, (5, 6, 4, 3)
TASKS = ("stack the cups", "open the drawer", "stack the cups", "wipe the table")


def _lerobot_frames(episode, length, camera):
  t = np.arange(length)[:, None, None, None]
  y, x = np.mgrid[0:SIZE, 0:SIZE]
  base = np.stack([x * 15, y * 15, np.full_like(x, 60 * episode + 100 * camera)], -1)[None]
  return ((base + 20 * t) % 256).astype(np.uint8)


def _lerobot_rows(episode, length, start_index):
  rng = np.random.default_rng(episode)
  return {"action": rng.normal(size=(length, 2)).astype(np.float32).tolist(),
          "actions.ee": rng.normal(size=(length, 4)).astype(np.float32).tolist(),
          "observation.state": rng.normal(size=(length, 3)).astype(np.float32).tolist(),
          "timestamp": (np.arange(length) / FPS).tolist(), "frame_index": list(range(length)),
          "episode_index": [episode] * length,
          "index": list(range(start_index, start_index + length)),
          "task_index": [TASKS.index(TASKS[episode])] * length}


def write_lerobot(root, version):
  """A LeRobot dataset of 4 episodes, 2 video cameras, 2-dim actions (and 4-dim ``actions.ee``),
  in layout v2.1 or v3.0."""
  cameras = ("observation.images.top", "observation.images.wrist")
  features = {"action": {"dtype": "float32", "shape": [2]},
              "actions.ee": {"dtype": "float32", "shape": [4]},
              "observation.state": {"dtype": "float32", "shape": [3]},
              **{c: {"dtype": "video", "shape": [SIZE, SIZE, 3],
                     "names": ["height", "width", "channels"]} for c in cameras}}
  os.makedirs(root / "meta")
  starts = np.cumsum((0,) + LENGTHS)
  if version == "v2":
    info = {"codebase_version": "v2.1", "fps": FPS, "chunks_size": 1000,
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"}
    with open(root / "meta" / "episodes.jsonl", "w") as f:
      for e, n in enumerate(LENGTHS):
        f.write(json.dumps({"episode_index": e, "tasks": [TASKS[e]], "length": n}) + "\n")
    for e, n in enumerate(LENGTHS):
      path = root / info["data_path"].format(episode_chunk=0, episode_index=e)
      os.makedirs(path.parent, exist_ok=True)
      pq.write_table(pa.table(_lerobot_rows(e, n, starts[e])), path)
      for c, camera in enumerate(cameras):
        video = root / info["video_path"].format(episode_chunk=0, video_key=camera, episode_index=e)
        os.makedirs(video.parent, exist_ok=True)
        write_video(str(video), _lerobot_frames(e, n, c), fps=FPS, scale=1)
  else:
    info = {"codebase_version": "v3.0", "fps": FPS,
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"}
    rows = [_lerobot_rows(e, n, starts[e]) for e, n in enumerate(LENGTHS)]
    path = root / "data" / "chunk-000" / "file-000.parquet"
    os.makedirs(path.parent)
    pq.write_table(pa.table({k: sum((r[k] for r in rows), []) for k in rows[0]}), path)
    episodes = {"episode_index": [], "tasks": [], "length": []}
    for c, camera in enumerate(cameras):
      video = root / "videos" / camera / "chunk-000" / "file-000.mp4"
      os.makedirs(video.parent)
      write_video(str(video), np.concatenate([_lerobot_frames(e, n, c) for e, n in
                                              enumerate(LENGTHS)]), fps=FPS, scale=1)
      episodes[f"videos/{camera}/chunk_index"] = [0] * len(LENGTHS)
      episodes[f"videos/{camera}/file_index"] = [0] * len(LENGTHS)
      episodes[f"videos/{camera}/from_timestamp"] = [float(s) / FPS for s in starts[:-1]]
    for e, n in enumerate(LENGTHS):
      episodes["episode_index"].append(e)
      episodes["tasks"].append([TASKS[e]])
      episodes["length"].append(n)
    path = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    os.makedirs(path.parent)
    pq.write_table(pa.table(episodes), path)
  info.update(features=features, splits={"train": f"0:{len(LENGTHS)}"},
              total_episodes=len(LENGTHS))
  with open(root / "meta" / "info.json", "w") as f:
    json.dump(info, f)
  return cameras


@pytest.mark.parametrize("version", ["v2", "v3"])
@pytest.mark.slow
def test_lerobot_import(tmp_path, version, monkeypatch):
  src = tmp_path / "src"
  cameras = write_lerobot(src, version)
  opened = []
  real_open = videoio.VideoStream._open
  monkeypatch.setattr(videoio.VideoStream, "_open",
                      lambda self: opened.append(self.path) or real_open(self))
  out = _cli("data", "import", "lerobot", str(src), str(tmp_path / "out"), "--camera",
             cameras[1]).strip().splitlines()[-1]
  episodes = ArrayRecordEpisodes(out, "train")  # the built-in `lerobot` spec
  assert episodes.spec.name == "lerobot" and episodes.spec.action_dim == 2
  assert episodes.lengths().tolist() == list(LENGTHS)
  top = ArrayRecordEpisodes(out, "train", oxe.specs_from_config(
      {"dataset": "lerobot", "image_key": "observation/top"}))
  for e, n in enumerate(LENGTHS):
    episode = episodes.episode(e)
    assert episode.instruction == TASKS[e]
    np.testing.assert_array_equal(episode.actions, np.asarray(_lerobot_rows(e, n, 0)["action"],
                                                              np.float32))
    for camera, source in ((cameras[1], episodes), (cameras[0], top)):
      if version == "v2":
        video = read_video(str(src / f"videos/chunk-000/{camera}/episode_{e:06d}.mp4"))
      else:
        first = sum(LENGTHS[:e])
        video = read_video(str(src / f"videos/{camera}/chunk-000/file-000.mp4"))[first:first + n]
      window = WindowSource(source, n, 1, None)
      frames = window[[int(i) for i, _ in window.index].index(e)]["frames"]
      np.testing.assert_array_equal(frames, video)  # PNG keeps the decoded video exactly
  # and what a training run reads: windows of a config split, with statistics of that split
  stats = action_stats(out, "train[:2]")
  assert stats.count == LENGTHS[0] - 1 + LENGTHS[1] - 1
  # the chosen camera is stored once, as observation/image; episodes keep the source's order
  observation = open_builder(out).info.features["steps"]["observation"]
  assert sorted(observation.keys()) == ["image", "state", "top"]
  assert [int(episodes._record(e)["episode_metadata"]["episode_id"]) for e in range(4)] == [0, 1, 2, 3]
  with pytest.raises(ValueError, match="already exists"):
    import_lerobot(str(src), out)
  other = import_lerobot(str(src), str(tmp_path / "ee"), action_key="actions.ee")
  # every video file is decoded once (v3: one file per camera holds all 4 episodes)
  assert len(opened) == len(set(opened)) == (8 if version == "v2" else 2)
  ee = ArrayRecordEpisodes(other, "train")
  assert ee.spec.action_dim == 4
  np.testing.assert_array_equal(ee.episode(3).actions, np.asarray(_lerobot_rows(3, 3, 0)["actions.ee"],
                                                                  np.float32))
  with pytest.raises(ValueError, match=r"the action 'act' \(--action_key names another; float "
                                       r"features: \['action', 'actions.ee', 'observation.state'\]"):
    import_lerobot(str(src), str(tmp_path / "x"), action_key="act")
  with pytest.raises(ValueError, match="no camera 'observation.images.side'"):
    import_lerobot(str(src), str(tmp_path / "other"), camera="observation.images.side")


@pytest.mark.slow
def test_own_lerobot_data_from_import_to_evaluation(tmp_path, capsys):
  """The own-data path of docs/data.md as a newcomer runs it: import, inspect, the training command
  inspect prints (at tiny widths), evaluate on the held-out split the config names."""
  from wmjax import cli
  src, out, workdir = tmp_path / "src", str(tmp_path / "data"), str(tmp_path / "run")
  write_lerobot(src, "v3")
  assert cli.main(["data", "import", "lerobot", str(src), out]) == 0
  printed, command = inspected_command(capsys, out, workdir)
  assert "this is the built-in 'lerobot' spec (2-dim actions" in printed
  assert "--config.model.action_dim=2" in command
  assert cli.main(command[1:] + [f"--config.{k}={v!r}" for k, v in OWN_DATA_TINY.items()]) == 0
  capsys.readouterr()
  assert cli.main(["evaluate", "--workdir", workdir, "--protocols", "long",
                   "--videos", "0"]) == 0
  assert "4 episodes: the last one is held out for evaluation" in printed
  results = json.loads((tmp_path / "run" / "eval" / "train[-1:]-step1" / "metrics.json")
                       .read_text())
  # the last of 4 episodes (3 steps) held out whole
  assert results["long"]["trajectories"] == 1
  assert np.isfinite(results["long"]["model"]["mse"]["mean"])
