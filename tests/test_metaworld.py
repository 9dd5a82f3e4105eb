"""The MetaWorld task: start states held out by construction, two cameras in the data, exact
replay, the reader's round trip and the command line's one-line errors."""

import dataclasses
import json
import os
import subprocess
import sys
import types

import numpy as np
import pytest

from conftest import ROOT
from wmjax import cli
from wmjax.config import load_config
from wmjax.data import synthetic
from wmjax.data.sources import ArrayRecordEpisodes
from wmjax.data.rlds import decode_image
from wmjax.tasks.metaworld import dataset, metrics, simulator  # sets MUJOCO_GL before mujoco loads
from wmjax.tasks.metaworld.reader import ArmReader, _init, degrade, fit_reader
from wmjax.tasks.metaworld.tracking import HandMotion, TrackedHand, fit_hand_motion

pytest.importorskip("metaworld", reason="needs the metaworld extra")

from wmjax.tasks.metaworld import evaluate  # noqa: E402  (the evaluation layer)

pytestmark = pytest.mark.integration
TINY = dataset.MetaWorldConfig(train_episodes=3, test_episodes=2, episode_length=4,
                               image_size=16)


def test_metaworld_evaluation_start_states_are_held_out_from_training():
  params = dataset.MetaWorldConfig(train_episodes=50, test_episodes=10)
  train = dataset.MetaWorld.start_states(params, "train")
  test = dataset.MetaWorld.start_states(params, "test")
  assert train.shape == (50, len(simulator.StartSpace.of(params.task).low))
  assert not synthetic.matching(test, train).any()
  states = evaluate.initial_states(params, 8)
  assert evaluate.held_out(params, states)
  assert not evaluate.held_out(params, np.concatenate([states, train[3:4]]))
  # the planning stream is not the evaluation stream
  planned = evaluate.initial_states(params, 8, purpose="plan")
  assert not synthetic.matching(planned, states).any()


# Written and replayed in one fresh process: MuJoCo's EGL crashes a process that has imported
# TensorFlow, as the test process has once another module ran. The replay reads an episode back
# from disk: its stored simulator state and action give the next step's state and frame.
PREPARE_AND_REPLAY = f"""
import dataclasses, sys
import numpy as np
from wmjax.data.rlds import decode_image
from wmjax.data.sources import ArrayRecordEpisodes
from wmjax.tasks.metaworld import dataset, simulator
params = dataset.MetaWorldConfig(**{dataclasses.asdict(TINY)!r})
directory = dataset.prepare(sys.argv[1], params)
source = ArrayRecordEpisodes(directory, "train")
source = ArrayRecordEpisodes(directory, "train", dataclasses.replace(
    source.spec, extra_keys=source.spec.extra_keys + ("observation/sim_state",)))
e = source.episode(0)
sim = simulator.ArmSimulator(params.task, params.views, params.image_size, params.action_repeat)
sim.reset(e.extras["start_state"][0])
np.testing.assert_allclose(sim.sim_state(), e.extras["sim_state"][0], atol=1e-6)
sim.restore(e.extras["sim_state"][1])
sim.step(e.actions[1])
np.testing.assert_allclose(sim.state(), e.extras["state"][2], atol=1e-5)
np.testing.assert_array_equal(sim.render()[0],
                              decode_image(e.images[2], None)[:, :params.image_size])
sim.close()
print("replayed", directory)
"""


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
  """The tiny dataset's builder directory, written (and an episode replayed) by
  ``PREPARE_AND_REPLAY``."""
  written = subprocess.run([sys.executable, "-c", PREPARE_AND_REPLAY,
                            str(tmp_path_factory.mktemp("metaworld"))], capture_output=True,
                           text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
  assert written.returncode == 0 and "replayed" in written.stdout, written.stderr[-2000:]
  return written.stdout.split()[-1]


def test_episodes_hold_both_cameras_side_by_side_and_replay_exactly(tiny_dataset):
  # the replay itself ran in the fixture's process
  source = ArrayRecordEpisodes(tiny_dataset, "train")
  assert len(source) == 3
  episode = source.episode(0)
  frame = decode_image(episode.images[0], None)
  assert frame.shape == (16, 32, 3)  # topview | gripperPOV
  views = metrics.split_views(frame[None])[0]
  assert not np.array_equal(views[0], views[1])
  noise = [float(source.episode(i).extras["policy_noise"][0]) for i in range(3)]
  assert noise == list(TINY.episode_noise(3))


def test_the_simulator_refuses_a_process_with_tensorflow(monkeypatch):
  monkeypatch.setitem(sys.modules, "tensorflow", types.ModuleType("tensorflow"))
  with pytest.raises(RuntimeError, match="crashes a process that has imported TensorFlow"):
    simulator.ArmSimulator(TINY.task, TINY.views, TINY.image_size)


def test_the_config_reads_the_dataset_as_two_views():
  config = load_config(str(ROOT / "configs" / "metaworld.py"))
  assert config.model.views == 2 and tuple(config.frame_shape) == (48, 96, 3)
  tiled = load_config(str(ROOT / "configs" / "metaworld.py:tiled"))
  assert tiled.model.views == 1 and tuple(tiled.frame_shape) == (48, 96, 3)


@pytest.mark.slow
def test_the_profile_trains_and_evaluates_two_views(tiny_dataset, tmp_path):
  """configs/metaworld.py at test size: two views side by side, the multi-view network, training's
  evaluation with per-view metrics."""
  data_dir = os.path.dirname(os.path.dirname(os.path.dirname(tiny_dataset)))  # DIR/name/cfg/ver
  workdir = tmp_path / "run"
  overrides = [f"data.data_dir={data_dir!r}", "data.metaworld.train_episodes=3",
               "data.metaworld.test_episodes=2", "data.metaworld.episode_length=4",
               "data.metaworld.image_size=16", "frame_shape=(16, 32, 3)", "model.patch_size=4",
               "model.depth=2", "model.hidden_size=32", "model.num_heads=2", "batch_size=8",
               "train.num_steps=2", "optim.total_steps=2", "optim.warmup_steps=1",
               "train.checkpoint_every=2", "train.eval_every=2", "train.eval_windows=2",
               "sampling.num_steps=2", "data.eval_stride=1"]
  assert cli.main(["train", "--config", str(ROOT / "configs" / "metaworld.py"), "--workdir",
                   str(workdir)] + [f"--config.{o}" for o in overrides]) == 0
  result = json.loads((workdir / "metrics.json").read_text())
  assert result["step"] == 2
  assert {"rollout_view0_mse", "rollout_view1_mse", "copy_last_view1_psnr"} <= set(result)


def test_reader_reads_per_view_and_round_trips(tmp_path):
  params = _init((8, 8, 8), 2, 16, 0)
  weights = np.array([[0.75] * 8, [0.25] * 8], np.float32)
  reader = ArmReader(params, np.zeros(8, np.float32), np.ones(8, np.float32), weights, 16, 2,
                     (8, 8, 8))
  frames = np.random.default_rng(0).integers(0, 256, (3, 16, 32, 3)).astype(np.uint8)
  read = reader.read(frames)
  assert read["per_view"].shape == (3, 2, 8) and read["success"].shape == (3,)
  np.testing.assert_allclose(read["state"], 0.75 * read["per_view"][:, 0, 2:]
                             + 0.25 * read["per_view"][:, 1, 2:], rtol=1e-5, atol=1e-6)
  again = ArmReader.load(reader.save(str(tmp_path / "reader"))).read(frames)
  np.testing.assert_allclose(again["per_view"], read["per_view"], rtol=1e-6)
  with pytest.raises(ValueError, match=r"frames \[N, 16, 32, 3\]"):
    reader.read(frames[:, :, :16])


def test_degrade_blurs_and_adds_noise_only_when_asked():
  import jax
  rng = np.random.default_rng(0)
  views = rng.uniform(-1, 1, (2, 4, 16, 16, 3)).astype(np.float32)
  key = jax.random.key(0)
  np.testing.assert_array_equal(np.asarray(degrade(views, key, 0.0, 0.0)), views)
  # a flat image stays flat under any blur; a textured one loses contrast; all stays in [-1, 1]
  flat = np.full((2, 4, 16, 16, 3), 0.3, np.float32)
  np.testing.assert_allclose(np.asarray(degrade(flat, key, 1.0, 0.0)), flat, atol=1e-6)
  blurred = np.asarray(degrade(views, key, 1.0, 0.0))
  assert blurred.std() < 0.9 * views.std()
  noisy = np.asarray(degrade(flat, key, 0.0, 0.5))
  assert noisy.std() > 0.01 and noisy.min() >= -1 and noisy.max() <= 1
  # each frame's views get the same degradation: two equal views stay equal
  pair = np.concatenate([views[:1], views[:1]])
  out = np.asarray(degrade(pair, key, 1.0, 0.0))
  np.testing.assert_allclose(out[0], out[1], atol=1e-6)
  with pytest.raises(ValueError, match=r"blur must lie in \[0, 1\]"):
    fit_reader(views[0], np.zeros((4, 8)), np.zeros(4), validation=None, blur=2.0)


def test_hand_motion_fits_a_lagged_hand_and_tracking_steadies_a_misread_frame():
  rng = np.random.default_rng(0)
  true = HandMotion(np.array([0.02, 0.015, 0.017]), np.array([0.026, 0.007, 0.023]))
  actions = rng.uniform(-1.5, 1.5, (20, 9, 4))  # clipped to [-1, 1] by the motion model
  hands = [np.zeros((20, 3))]
  for t in range(9):
    previous = actions[:, t - 1] if t else np.zeros((20, 4))
    hands.append(hands[-1] + np.stack([true.move(a, p) for a, p in zip(actions[:, t], previous)]))
  fitted = HandMotion.fit(np.stack(hands, 1), actions)
  np.testing.assert_allclose(fitted.now, true.now, atol=1e-9)
  np.testing.assert_allclose(fitted.before, true.before, atol=1e-9)
  with pytest.raises(ValueError, match=r"need hands \[N, T, 3\] and actions \[N, T-1, A\]"):
    HandMotion.fit(np.stack(hands, 1), actions[:, :3])
  # the same episode read with its fifth frame's hand misread by 6 cm: the newest reading alone
  # takes the error whole, a tracker a third of it; both keep the object's newest reading
  newest, tracked = TrackedHand(None), TrackedHand(true, reading_weight=1 / 3)
  for t in range(5):
    reading = np.concatenate([hands[t][0], [0.1, 0.2, 0.3 + t]])
    reading[0] += 0.06 if t == 4 else 0.0
    states = [tracker.update(reading) for tracker in (newest, tracked)]
    for tracker in (newest, tracked):
      tracker.acted(actions[0, t])
    for state in states:
      np.testing.assert_allclose(state[3:], reading[3:], rtol=1e-6)
  errors = [np.linalg.norm(state[:3] - hands[4][0]) for state in states]
  np.testing.assert_allclose(errors, [0.06, 0.02], atol=1e-6)
  with pytest.raises(ValueError, match="needs a HandMotion"):
    TrackedHand(None, reading_weight=0.5)


def test_policy_evaluation_refuses_fewer_than_three_policies_before_simulating(tmp_path):
  with pytest.raises(ValueError, match=r"at least 3 of them, got 2: \['expert', 'idle'\]"):
    evaluate.evaluate_policies(None, None, str(tmp_path), specs=("expert", "idle"))
  assert not any(tmp_path.iterdir())


def test_hand_motion_fits_on_the_training_data_and_names_it_when_missing(tiny_dataset, tmp_path):
  motion = fit_hand_motion(tiny_dataset)
  assert motion.now.shape == motion.before.shape == (3,)
  assert np.isfinite(motion.now).all() and np.isfinite(motion.before).all()
  config = load_config(str(ROOT / "configs" / "metaworld.py"), [
      f"data.data_dir={str(tmp_path)!r}", "data.metaworld.train_episodes=3"])
  with pytest.raises(FileNotFoundError, match="wmjax data prepare metaworld"):
    evaluate.training_hand_motion(config)
  data_dir = os.path.dirname(os.path.dirname(os.path.dirname(tiny_dataset)))  # DIR/name/cfg/ver
  config = load_config(str(ROOT / "configs" / "metaworld.py"), [
      f"data.data_dir={data_dir!r}"] + [f"data.metaworld.{k}={v!r}" for k, v in
                                         dataclasses.asdict(TINY).items() if k != "views"])
  np.testing.assert_allclose(evaluate.training_hand_motion(config).now, motion.now)


@pytest.mark.parametrize("flag,message", [
    ("--task=push-v9", "unknown MetaWorld task 'push-v9'; valid tasks: button-press-v3"),
    ("--views=topview,wrist", "unknown camera(s) ['wrist']; valid cameras: topview"),
])
def test_prepare_names_the_valid_tasks_and_cameras(tmp_path, capsys, flag, message):
  assert cli.main(["data", "prepare", "metaworld", "--data_dir", str(tmp_path), flag]) != 0
  err = capsys.readouterr().err
  assert message in err and len(err.strip().splitlines()) == 1
  assert not any(tmp_path.iterdir())
