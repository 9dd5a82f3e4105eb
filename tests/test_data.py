"""Data layer: Open-X specs, both read paths, statistics, grain pipeline, gridworld, global batches."""

import json
import subprocess
import sys

import jax
import numpy as np
import pytest
import tensorflow_datasets as tfds

import oxe_fixtures
from wmjax.data import oxe
from wmjax.data.convert import convert_to_array_record
from wmjax.data.pipeline import WindowSource, training_pipeline
from wmjax.data.rlds import episode_windows
from wmjax.data.sources import (ArrayRecordEpisodes, action_stats, episode_split, stats_filename,
                                 tfrecord_episodes)
from wmjax.data.stats import ActionStats
from wmjax.parallel import global_batch
from wmjax.tasks.gridworld import dataset as gridworld

FRAMES, STRIDE = 4, 2


@pytest.fixture(scope="module")
def oxe_data(tmp_path_factory):
  """name -> (TFRecord builder dir, ArrayRecord builder dir) of every Open-X fixture."""
  root = tmp_path_factory.mktemp("oxe")
  dirs = {}
  for name in oxe_fixtures.FEATURES:
    tfrecord = oxe_fixtures.build(name, str(root / "tfrecord"))
    dirs[name] = (tfrecord, str(convert_to_array_record(tfrecord, root / "array_record" / name)))
  return dirs


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
  config = gridworld.GridworldConfig(train_episodes=24, test_episodes=4, episode_length=12)
  return gridworld.prepare(str(tmp_path_factory.mktemp("grid")), config), config


@pytest.mark.integration
@pytest.mark.parametrize("name", sorted(oxe_fixtures.FEATURES))
@pytest.mark.slow
def test_both_read_paths_yield_identical_windows(oxe_data, name, caplog):
  tfrecord_dir, array_record_dir = oxe_data[name]
  episodes = ArrayRecordEpisodes(array_record_dir, "train")
  with caplog.at_level("WARNING", logger="wmjax.data.pipeline"):
    source = WindowSource(episodes, FRAMES, STRIDE, episodes.spec.resolution)
  assert f"skipped 1 of 3 episodes shorter than the {FRAMES}-frame window" in caplog.text
  streamed = [w for i, episode in enumerate(tfrecord_episodes(tfrecord_dir, "train"))
              for w in episode_windows(episode, FRAMES, STRIDE, episodes.spec.resolution, i)]
  # episodes of 5, 3 and 7 steps: windows start at 0 | (too short, skipped) | 0, 2
  assert len(source) == len(streamed) == 3
  assert source.num_skipped_episodes == 1
  h, w = episodes.spec.resolution
  for a, b in zip(streamed, (source[k] for k in range(len(source)))):
    assert a["frames"].shape == (FRAMES, h, w, 3) and a["frames"].dtype == np.uint8
    assert a["actions"].shape == (FRAMES - 1, episodes.spec.action_dim)
    np.testing.assert_array_equal(a["frames"], b["frames"])
    np.testing.assert_array_equal(a["actions"], b["actions"])
    assert a["instruction"] == b["instruction"]
    assert (a["episode"], a["start"]) == (b["episode"], b["start"])
  assert [w["instruction"] for w in streamed] == [
      oxe_fixtures.INSTRUCTIONS[0].encode(), oxe_fixtures.INSTRUCTIONS[2].encode(),
      oxe_fixtures.INSTRUCTIONS[2].encode()]


@pytest.mark.integration
@pytest.mark.parametrize("name", sorted(oxe_fixtures.FEATURES))
def test_window_actions_are_the_standardised_raw_actions(oxe_data, name):
  """Windows carry exactly the raw published actions, concatenated into the IRASim space."""
  _, array_record_dir = oxe_data[name]
  builder = tfds.builder_from_directory(array_record_dir)
  steps = builder.as_data_source()["train"][2]["steps"]
  episodes = ArrayRecordEpisodes(array_record_dir, "train")
  window = WindowSource(episodes, FRAMES, STRIDE, (16, 16))[2]  # episode 2, start 2
  assert (window["episode"], window["start"]) == (2, 2)
  for j in range(FRAMES - 1):
    a = steps[2 + j]["action"]
    if name == "fractal20220817_data":
      expected = [*a["world_vector"], *a["rotation_delta"], *a["gripper_closedness_action"]]
    elif name == "bridge":
      expected = [*a["world_vector"], *a["rotation_delta"], float(a["open_gripper"])]
    else:  # bridge_dataset (7-dim) and language_table (2-dim) publish the action as it is
      expected = list(a)
    np.testing.assert_array_equal(window["actions"][j], np.asarray(expected, np.float32))


@pytest.mark.unit
def test_standardisation_by_hand():
  rt1 = oxe.SPECS["fractal20220817_data"][0]
  steps = {"action": {"world_vector": np.array([[1, 2, 3]]), "rotation_delta": np.array([[4, 5, 6]]),
                      "gripper_closedness_action": np.array([[0.5]])}}
  np.testing.assert_array_equal(rt1.actions(steps), [[1, 2, 3, 4, 5, 6, 0.5]])
  bridge_oxe = oxe.SPECS["bridge"][0]
  steps = {"action": {"world_vector": np.array([[1, 2, 3]]), "rotation_delta": np.array([[4, 5, 6]]),
                      "open_gripper": np.array([True])}}
  np.testing.assert_array_equal(bridge_oxe.actions(steps), [[1, 2, 3, 4, 5, 6, 1.0]])
  language_table = oxe.SPECS["language_table"][0]
  np.testing.assert_array_equal(language_table.actions({"action": np.array([[0.1, -0.2]])}),
                                np.array([[0.1, -0.2]], np.float32))
  codes = np.zeros(512, np.int32)
  codes[:5] = list(b"push ")
  assert oxe.decode_instruction(codes) == "push "
  assert oxe.decode_instruction(np.zeros(512, np.int32)) == ""
  assert oxe.decode_instruction(b"pick") == "pick"


@pytest.mark.integration
def test_missing_key_error_lists_expected_and_found(oxe_data):
  features = tfds.builder_from_directory(oxe_data["bridge_dataset"][1]).info.features
  with pytest.raises(ValueError) as error:
    oxe.resolve_spec("fractal20220817_data", features)
  message = str(error.value)
  assert "observation/natural_language_instruction" in message  # expected
  assert "observation/image_0" in message  # found
  with pytest.raises(ValueError, match="unknown dataset 'rt2'"):
    oxe.resolve_spec("rt2", features)
  # both Bridge layouts resolve under both names
  assert oxe.resolve_spec("bridge", features).layout == "bridge_v2"
  old = tfds.builder_from_directory(oxe_data["bridge"][1]).info.features
  assert oxe.resolve_spec("bridge_dataset", old).layout == "oxe"


@pytest.mark.integration
def test_converted_equals_written_by_tfds_as_array_record(oxe_data, tmp_path):
  written = oxe_fixtures.build("language_table", str(tmp_path), file_format="array_record")
  a = ArrayRecordEpisodes(written, "train")
  b = ArrayRecordEpisodes(oxe_data["language_table"][1], "train")
  assert len(a) == len(b) == 3
  for i in range(3):
    ea, eb = a.episode(i), b.episode(i)
    assert ea.images == eb.images and ea.instruction == eb.instruction
    np.testing.assert_array_equal(ea.actions, eb.actions)


@pytest.mark.integration
@pytest.mark.slow
def test_worker_processes_yield_the_same_batches(grid):
  builder_dir, _ = grid
  source = WindowSource(ArrayRecordEpisodes(builder_dir, "train"), 6, 1, None)
  stats = action_stats(builder_dir)
  batches = [_batches(iter(training_pipeline([source], [stats], batch_size=4, seed=1,
                                             shard_index=0, shard_count=1, num_workers=w)), 3)
             for w in (0, 1)]
  for a, b in zip(*batches):
    np.testing.assert_array_equal(a["frames"], b["frames"])
    np.testing.assert_array_equal(a["actions"], b["actions"])


@pytest.mark.integration
def test_window_source_reads_only_the_episodes_named(grid):
  builder_dir, _ = grid
  episodes = ArrayRecordEpisodes(builder_dir, "train")
  every = WindowSource(episodes, 6, 1, None)
  some = WindowSource(episodes, 6, 1, None, only=[3, 1, 3])
  assert sorted(set(some.index[:, 0])) == [1, 3]
  np.testing.assert_array_equal(some.index, every.index[np.isin(every.index[:, 0], [1, 3])])
  np.testing.assert_array_equal(some[0]["frames"], every[int(np.flatnonzero(every.index[:, 0] == 1)[0])]["frames"])
  with pytest.raises(ValueError, match=r"episode indices must lie in \[0, "):
    WindowSource(episodes, 6, 1, None, only=[len(episodes)])


@pytest.mark.integration
def test_random_access_needs_array_record(oxe_data):
  with pytest.raises(ValueError, match="wmjax data convert"):
    ArrayRecordEpisodes(oxe_data["language_table"][0], "train")
  with pytest.raises(ValueError, match="already exists"):
    convert_to_array_record(oxe_data["language_table"][0], oxe_data["language_table"][1])


@pytest.mark.integration
def test_action_stats_round_trip_and_normalisation(oxe_data, tmp_path):
  stats = action_stats(oxe_data["fractal20220817_data"][1])
  assert stats.gripper_dim == 6 and stats.count == 5 + 3 + 7 - 3  # last step of each episode out
  again = ActionStats.from_dict(json.loads(json.dumps(stats.to_dict())))
  for field in ("mean", "std", "p01", "p99", "min", "max"):
    np.testing.assert_array_equal(getattr(again, field), getattr(stats, field))
  assert (again.dataset, again.count, again.gripper_dim) == (stats.dataset, stats.count, 6)
  # cached beside the data: the same numbers come back without recomputation
  builder_dir = oxe_data["fractal20220817_data"][1]
  spec = ArrayRecordEpisodes(builder_dir, "train").spec
  cached = json.loads(open(f"{builder_dir}/{stats_filename('train', spec)}").read())
  assert ActionStats.from_dict(cached).to_dict() == stats.to_dict() and cached["split"] == "train"

  by_hand = ActionStats.compute(np.array([[0.0, 10.0, 1.0], [2.0, 30.0, 0.0]]), "toy", gripper_dim=2)
  np.testing.assert_allclose(by_hand.mean, [1, 20, 0.5])
  np.testing.assert_allclose(by_hand.std, [1, 10, 0.5])
  actions = np.array([[3.0, 40.0, 1.0]])
  np.testing.assert_allclose(by_hand.normalize(actions), [[2.0, 2.0, 1.0]])
  np.testing.assert_allclose(by_hand.p01, [0.02, 10.2, 0.01])
  np.testing.assert_allclose(by_hand.normalize(np.array([[1.0, 20.0, 0.0]]), "bounds"),
                             [[0.0, 0.0, 0.0]], atol=1e-6)
  np.testing.assert_allclose(by_hand.normalize(actions, "bounds"), [[1.0, 1.0, 1.0]])
  with pytest.raises(ValueError, match="dimension 2"):
    by_hand.normalize(np.zeros((1, 2)))
  with pytest.raises(ValueError, match="lack"):
    ActionStats.from_dict({"dataset": "x"})


def _batches(iterator, n):
  return [next(iterator) for _ in range(n)]


@pytest.mark.integration
def test_grain_iterator_state_restores_exactly(grid):
  builder_dir, _ = grid
  source = WindowSource(ArrayRecordEpisodes(builder_dir, "train"), 6, 1, None)
  stats = action_stats(builder_dir)
  make = lambda: iter(training_pipeline([source], [stats], batch_size=4, seed=3, shard_index=0,
                                        shard_count=1))
  it = make()
  _batches(it, 5)
  state = it.get_state()
  expected = _batches(it, 4)
  fresh = make()
  fresh.set_state(state)
  for a, b in zip(expected, _batches(fresh, 4)):
    assert a.keys() == b.keys()
    for key in a:
      np.testing.assert_array_equal(a[key], b[key])
  first = next(make())
  assert first["frames"].dtype == np.float32 and -1 <= first["frames"].min() < first["frames"].max() <= 1
  k = [tuple(ix) for ix in source.index.tolist()].index((first["episode"][0], first["start"][0]))
  raw = source[k]
  np.testing.assert_allclose(first["actions"][0], stats.normalize(raw["actions"]), rtol=1e-6)
  np.testing.assert_allclose(first["frames"][0], raw["frames"] / 127.5 - 1.0, atol=1e-6)


@pytest.mark.integration
def test_process_shards_are_disjoint_and_cover_the_data(grid):
  builder_dir, _ = grid
  source = WindowSource(ArrayRecordEpisodes(builder_dir, "train"), 6, 3, None)
  stats = action_stats(builder_dir)
  seen = []
  for shard in range(3):
    ds = training_pipeline([source], [stats], batch_size=1, shard_index=shard, shard_count=3,
                           shuffle=True, repeat=False, drop_remainder=False)
    seen.append({(int(b["episode"][0]), int(b["start"][0])) for b in ds})
  assert not (seen[0] & seen[1] or seen[0] & seen[2] or seen[1] & seen[2])
  everything = {(int(e), int(s)) for e, s in source.index}
  assert seen[0] | seen[1] | seen[2] == everything
  assert abs(len(seen[0]) - len(seen[2])) <= 1


@pytest.mark.integration
def test_weighted_mixture(grid, tmp_path):
  builder_dir, config = grid
  other = gridworld.prepare(str(tmp_path), gridworld.GridworldConfig(
      num_squares=1, train_episodes=8, test_episodes=2, episode_length=12))
  sources = [WindowSource(ArrayRecordEpisodes(d, "train"), 6, 1, None) for d in (builder_dir, other)]
  stats = [action_stats(builder_dir), action_stats(other)]
  ds = training_pipeline(sources, stats, weights=[3, 1], batch_size=8, shard_index=0, shard_count=1)
  batches = _batches(iter(ds), 25)
  share = np.mean(np.concatenate([b["source"] for b in batches]) == 0)
  assert abs(share - 0.75) < 0.05
  # the 1-square dataset's 2-dim actions are zero-padded to the mixture's 4
  padded = np.concatenate([b["actions"][b["source"] == 1] for b in batches])
  assert padded.shape[-1] == 4 and (padded[..., 2:] == 0).all() and (padded[..., :2] != 0).any()


@pytest.mark.integration
def test_gridworld_positions_follow_the_actions(grid):
  builder_dir, config = grid
  episodes = ArrayRecordEpisodes(builder_dir, "train")
  assert episodes.spec.action_dim == 2 * config.num_squares
  episode = episodes.episode(0)
  positions = episode.extras["square_positions"]  # [L, n, 2]
  half = config.square_size / 2
  # positions snap to the pixel grid: the frame shows the whole state
  moved = np.round(positions[:-1] + episode.actions[:-1].reshape(-1, config.num_squares, 2)
                   - half) + half
  np.testing.assert_allclose(positions[1:], np.clip(moved, half, config.image_size - half),
                             atol=1e-5)
  assert np.abs(episode.actions).max() > 0.5 and (positions[1:] != positions[:-1]).any()
  window = WindowSource(episodes, 4, 1, None)[0]
  for i, (cy, cx) in enumerate(window["square_positions"][0]):
    if i == config.num_squares - 1:  # the top square is fully visible at its centre
      np.testing.assert_array_equal(window["frames"][0, int(cy), int(cx)], gridworld.COLORS[i])


@pytest.mark.unit
def test_gridworld_without_snapping_keeps_sub_pixel_positions():
  config = gridworld.GridworldConfig(snap_to_pixels=False, episode_length=8)
  centres, actions = gridworld.simulate(config, np.random.default_rng(0))
  half = config.square_size / 2
  moved = np.clip(centres[:-1] + actions[:-1].reshape(-1, config.num_squares, 2), half,
                  config.image_size - half)
  np.testing.assert_allclose(centres[1:], moved, atol=1e-5)
  assert not np.allclose(centres, np.round(centres - half) + half)
  assert config.name != gridworld.GridworldConfig(episode_length=8).name


@pytest.mark.integration
def test_prepare_gridworld_command(tmp_path):
  out = subprocess.run([sys.executable, "-m", "wmjax.cli", "data", "prepare", "gridworld",
                        "--data_dir", str(tmp_path), "--train_episodes", "3", "--test_episodes",
                        "1", "--episode_length", "5"], capture_output=True, text=True, check=True)
  builder_dir = out.stdout.strip().splitlines()[-1]
  assert len(ArrayRecordEpisodes(builder_dir, "train")) == 3
  assert ArrayRecordEpisodes(builder_dir, "test").lengths().tolist() == [5]


@pytest.mark.unit
def test_global_batch_is_sharded_over_the_batch_axes():
  mesh = jax.make_mesh((2, 4, 1), ("data", "fsdp", "tensor"),
                       axis_types=(jax.sharding.AxisType.Auto,) * 3)
  local = {"frames": np.arange(8 * 3, dtype=np.float32).reshape(8, 3), "instruction": np.array([b"x"] * 8)}
  batch = global_batch(local, mesh)
  assert set(batch) == {"frames"}
  assert batch["frames"].sharding.shard_shape((8, 3)) == (1, 3)
  np.testing.assert_array_equal(np.asarray(batch["frames"]), local["frames"])
  expected = (r"global batch 6 is not divisible by the data-parallel size 8 "
              r"\(mesh data x fsdp = 2 x 4\): expected a multiple of 8, got 6")
  with pytest.raises(ValueError, match=expected):
    global_batch({"frames": np.zeros((6, 3), np.float32)}, mesh)


@pytest.mark.integration
def test_an_empty_split_says_so_and_how_to_name_episodes(grid):
  builder_dir, _ = grid
  with pytest.raises(ValueError, match=r"the split 'test\[4:\]' of .* is empty \(4 episodes"):
    ArrayRecordEpisodes(builder_dir, "test[4:]")
  assert ArrayRecordEpisodes(builder_dir, "test[-1:]").lengths().shape == (1,)
  assert len(ArrayRecordEpisodes(builder_dir, "test[90%:]")) == 1  # TFDS would give none


@pytest.mark.unit
def test_percent_splits_hold_out_an_episode_of_two_or_more():
  assert [episode_split(s, 3) for s in ("train[:90%]", "train[90%:]")] == ["train[:2]", "train[2:]"]
  assert [episode_split(s, 2) for s in ("train[:95%]", "train[95%:]")] == ["train[:1]", "train[1:]"]
  # where TFDS rounding keeps both sides non-empty, its boundary is kept
  assert [episode_split(s, 100) for s in ("train[:95%]", "train[95%:]")] == ["train[:95]",
                                                                             "train[95:]"]
  assert episode_split("train[-10%:]", 3) == "train[2:]"
  assert episode_split("train[90%:]", 1) == "train[1:]"  # one episode cannot be shared: empty
  for unchanged in ("test", "train[7:8]", "train[:-1]"):
    assert episode_split(unchanged, 3) == unchanged
