"""Push-T: frame geometry against the simulator, the scripted pusher, the dataset, the reward
functions, and `wmjax eval-policy` / `wmjax plan` end to end on a tiny model."""

import dataclasses
import json
import os
import shutil
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image

from conftest import PUSHT_EXPERIMENT_TINY, ROOT, pusht_experiment_script
from wmjax import cli
from wmjax.config import load_config
from wmjax.data import synthetic
from wmjax.data.sources import ArrayRecordEpisodes, open_dataset
from wmjax.eval import rewards
from wmjax.frames import to_model
from wmjax.tasks.pusht import dataset as pusht_data
from wmjax.tasks.pusht import metrics as pusht_metrics
from wmjax.tasks.pusht import simulator as pusht
from wmjax.tasks.gridworld import dataset as gridworld_data
from wmjax.tasks.pusht.evaluate import actions_for, held_out, initial_states, summarize
from wmjax.tasks.pusht.rewards import coverage


def _render(states, size=48):
  frames, info = pusht.PushTSimulator(len(states), size).reset(np.asarray(states))
  return frames, info


@pytest.mark.unit
def test_frame_coverage_and_centroids_follow_the_simulator():
  rng = np.random.default_rng(0)
  states = np.concatenate([pusht.reset_state((60, 60), pusht.GOAL_POSE[:2], pusht.GOAL_POSE[2])[None],
                           pusht.random_initial_states(rng, 24, max_offset=150, max_angle=1.5)])
  frames, info = _render(states, 96)
  assert info["coverage"][0] == pytest.approx(1.0)
  estimate = np.asarray(pusht.frame_coverage(to_model(frames)))
  assert estimate[0] > 0.97
  assert np.corrcoef(estimate, info["coverage"])[0, 1] > 0.95
  block, agent, seen = (np.asarray(x) for x in pusht.centroids(to_model(frames)))
  assert seen.all()
  np.testing.assert_allclose(agent, info["state"][:, :2], atol=6.0)
  # the block's centre of area, in the world, from its body pose
  centre = np.stack([pusht.body_to_world(np.array(pusht.T_CENTROID), (x, y, a))
                     for x, y, a in info["state"][:, 2:]])
  np.testing.assert_allclose(block, centre, atol=12.0)  # the agent may hide part of the block
  np.testing.assert_allclose(pusht.goal_mask(512).sum(), 6300, rtol=0.02)  # the T's area


@pytest.mark.unit
def test_stay_holds_the_newest_agent_a_frame_shows():
  background = np.full((3, 2, 48, 48, 3), 255, np.uint8)
  agent = np.asarray(pusht.PALETTE[pusht.PALETTE_NAMES.index("agent")], np.uint8)
  frames = background.copy()
  frames[0, 0, 10:13, 30:33] = agent  # episode 0: seen in the older frame only
  frames[1, 0, 10:13, 30:33] = agent  # episode 1: seen in both, moved in the newer
  frames[1, 1, 40:43, 5:8] = agent
  chunk = np.asarray(pusht.StayPolicy(chunk=2)(to_model(frames), jax.random.key(0)))
  assert chunk.shape == (3, 2, 2)
  cell = pusht.WORKSPACE / 48
  np.testing.assert_allclose(chunk[0, 0], [31.5 * cell, 11.5 * cell])  # (x, y) of the older
  np.testing.assert_allclose(chunk[1, 1], [6.5 * cell, 41.5 * cell])  # the newer one
  np.testing.assert_allclose(chunk[2, 0], [256.0, 256.0])  # none shows it: the centre


@pytest.mark.unit
def test_agent_and_block_metrics_read_from_frames():
  """A perfect prediction scores 0 px / IoU 1; an agent moved by 3 cells of 512/48 px is 3
  pixels off; an erased agent is not found and costs half the frame."""
  rng = np.random.default_rng(1)
  agents = np.array([[100.0, 400.0], [400.0, 100.0]])
  states = pusht.random_initial_states(rng, 2)
  states[:, :2] = agents
  truth, _ = _render(states)
  moved = states.copy()
  moved[:, 0] += 3 * 512 / 48
  shifted, _ = _render(moved)
  erased = truth.copy()
  erased[np.asarray(pusht.object_masks(to_model(truth))[1])] = 255
  pred = np.stack([truth, shifted, erased], 1)  # [E=2, T=3, 48, 48, 3]
  got = pusht_metrics.pusht_metrics(pred, np.repeat(truth[:, None], 3, 1), {})
  assert {k: v.shape for k, v in got.items()} == {
      k: (2, 3) for k in ("agent_error_px", "agent_found", "agent_iou", "block_error_px",
                          "block_angle_error_deg", "block_iou")}
  np.testing.assert_allclose(got["agent_error_px"][:, 0], 0.0)
  np.testing.assert_allclose(got["agent_error_px"][:, 1], 3.0, atol=0.6)
  np.testing.assert_allclose(got["agent_error_px"][:, 2], 24.0)
  np.testing.assert_allclose(got["agent_found"], [[1, 1, 0]] * 2)
  np.testing.assert_allclose(got["agent_iou"][:, 0], 1.0)
  assert (got["agent_iou"][:, 1:] == 0).all()  # moved by its own width / gone
  np.testing.assert_allclose(got["block_iou"][:, 0], 1.0)
  assert (got["block_error_px"][:, :2] < 0.5).all()  # the agent off the block: the T unchanged
  assert (got["block_angle_error_deg"][:, :2] < 3.0).all()
  masks = pusht_metrics.pusht_masks(pred, np.repeat(truth[:, None], 3, 1), {})
  assert masks.shape == (2, 3, 48, 48) and masks[:, 1].sum() > masks[:, 0].sum()


@pytest.mark.unit
def test_block_pose_reads_the_angle_of_the_t_from_frames():
  """Any angle, anywhere (the T rotated all the way round: the stem's end is told from the
  bar's), within a few degrees at 48 px; a T turned by 30 degrees is 30 degrees off, a missing
  one 180."""
  states = pusht.random_initial_states(np.random.default_rng(5), 32, max_offset=150,
                                       max_angle=3.1)
  frames, info = _render(states)
  block = np.asarray(pusht.object_masks(to_model(frames))[0])
  _, angle, found = pusht_metrics.block_pose(block)
  error = np.degrees(np.angle(np.exp(1j * (angle - info["state"][:, 4]))))
  assert found.all() and np.abs(error).mean() < 5 and np.abs(error).max() < 15, error
  turned = states.copy()
  turned[:, 4] += np.radians(30)
  turned_frames, _ = _render(turned)
  blank = np.full_like(frames, 255)
  got = pusht_metrics.pusht_metrics(np.stack([turned_frames, blank], 1),
                                    np.stack([frames, frames], 1), {})
  np.testing.assert_allclose(np.median(got["block_angle_error_deg"][:, 0]), 30, atol=4)
  np.testing.assert_allclose(got["block_angle_error_deg"][:, 1], 180.0)


@pytest.mark.unit
@pytest.mark.parametrize("profile", ["cpu", "h100"])
def test_pusht_evaluation_and_planning_start_states_are_held_out_from_training(profile):
  """Policy evaluation and planning draw their start states from streams no split draws from:
  none equals (to 1e-6) a start state of the config's training split, for several evaluation
  seeds. The check catches the states the evaluation drew before (the training split's own
  stream, ``default_rng(0)``): most of them were training start states."""
  config = load_config(str(ROOT / "configs" / f"pusht.py:{profile}"))
  params = pusht_data.PushTConfig.from_dict(config.data.pusht)
  train = pusht_data.PushT.start_states(params, "train")
  assert train.shape == (params.train_episodes, 5)
  for purpose, count in (("evaluate", 48), ("plan", 20)):
    for seed in range(3):
      states = initial_states(config, count, purpose, seed)
      assert not synthetic.matching(states, train).any(), (purpose, seed)
      assert held_out(config, states) is True
  test_split = pusht_data.PushT.start_states(params, "test")
  assert not synthetic.matching(test_split, train).any()
  old = pusht.random_initial_states(np.random.default_rng(params.seed), 48,
                                    max_offset=params.max_offset, max_angle=params.max_angle)
  assert synthetic.matching(old, train).sum() >= 40
  assert held_out(config, old) is False


@pytest.mark.unit
def test_gridworld_evaluation_start_states_are_held_out_from_training():
  """The gridworld is evaluated on its test split (``data.eval_split``): no test episode starts
  where a training episode starts (positions on a 13 x 13 grid per square, so a collision is
  possible and is checked, not assumed)."""
  config = load_config(str(ROOT / "configs" / "gridworld.py"))
  assert (config.data.train_split, config.data.eval_split) == ("train", "test")
  params = gridworld_data.GridworldConfig.from_dict(config.data.gridworld)
  train = gridworld_data.Gridworld.start_states(params, "train")
  test = gridworld_data.Gridworld.start_states(params, "test")
  assert train.shape == (params.train_episodes, params.num_squares, 2)
  assert test.shape == (params.test_episodes, params.num_squares, 2)
  assert not synthetic.matching(test, train).any()
  assert synthetic.matching(train[5:9], train).all()  # the check finds what is there


@pytest.mark.unit
def test_random_streams_are_separate_per_purpose():
  draws = {purpose: synthetic.stream(0, purpose).uniform(size=4)
           for purpose in ("train", "test", "evaluate", "plan")}
  draws["evaluate seed 1"] = synthetic.stream(0, "evaluate", 1).uniform(size=4)
  values = np.stack(list(draws.values()))
  assert len(np.unique(values[:, 0])) == len(values)
  np.testing.assert_array_equal(draws["train"], np.random.default_rng(0).uniform(size=4))
  with pytest.raises(ValueError, match="purpose must be one of"):
    synthetic.stream(0, "validation")


@pytest.mark.unit
def test_the_pusher_beats_staying_and_noise_hurts():
  states = pusht.random_initial_states(np.random.default_rng(1), 12)
  final = {}
  for spec in ("push", "push:0.5", "stay"):
    run = pusht.simulate_policy(pusht.policy_from_spec(spec, 4), states, 24, image_size=48,
                                key=jax.random.key(0), context=2)
    assert run["frames"].shape == (12, 26, 48, 48, 3) and run["actions"].shape == (12, 25, 2)
    np.testing.assert_allclose(run["actions"][:, 0], states[:, :2], atol=1e-3)  # the still step
    final[spec] = run["coverage"][:, -1].mean()
  assert final["push"] > final["stay"] + 0.05 and final["push"] > final["push:0.5"] + 0.05
  with pytest.raises(ValueError, match="policy spec"):
    pusht.policy_from_spec("teleport", 4)


@pytest.mark.unit
def test_episode_lengths_default_to_the_same_time_whatever_the_action_repeat():
  """eval-policy's and plan's default --steps (and run.py's): actions of a given number of
  control steps, each held action_repeat of them."""
  held = load_config(str(ROOT / "configs" / "pusht.py"))
  each = load_config(str(ROOT / "configs" / "pusht.py"), ["data.pusht.action_repeat=1"])
  assert (actions_for(held, 24), actions_for(each, 24), actions_for(held, 3)) == (6, 24, 1)


@pytest.mark.unit
def test_action_repeat_is_a_frame_per_held_action():
  """``action_repeat = k``: one step holds its target for k control steps and returns the last
  frame, so a chunk of k equal targets at one frame a step ends where one repeated step does,
  and the repeated run's frames are every k-th of the stepped run's."""
  states = pusht.random_initial_states(np.random.default_rng(2), 3)
  stepped = pusht.simulate_policy(pusht.PushPolicy(chunk=4), states, 16, image_size=32,
                                  key=jax.random.key(0), context=2)
  held = pusht.simulate_policy(pusht.PushPolicy(chunk=1), states, 4, image_size=32,
                               key=jax.random.key(0), context=2, action_repeat=4)
  assert held["frames"].shape == (3, 6, 32, 32, 3)
  np.testing.assert_array_equal(held["frames"][:, 2:], stepped["frames"][:, 5::4])
  np.testing.assert_allclose(held["state"][:, -1], stepped["state"][:, -1], atol=1e-4)
  assert pusht_data.PushTConfig(action_repeat=4).name.endswith("_k4")
  assert "_k" not in pusht_data.PushTConfig().name
  with pytest.raises(ValueError, match="action_repeat"):
    pusht.PushTSimulator(1, 32, action_repeat=0)


@pytest.mark.unit
def test_config_profiles():
  cpu, latent, h100 = (load_config(str(ROOT / "configs" / f"pusht.py:{p}"))
                       for p in ("cpu", "latent", "h100"))
  assert (cpu.model.depth, cpu.batch_size, cpu.model.dtype) == (6, 16, "float32")
  for profile in (cpu, h100):  # one recipe: the next frame from two clean ones, in 8 DDIM steps
    assert (profile.model.num_frames, profile.rollout.context, profile.rollout.horizon) == (3, 2, 1)
    assert (profile.diffusion.prediction, profile.sampling.num_steps) == ("x0", 8)
    # a frame per decision (each action held 4 control steps), agents that touch the T from
    # every side and idle ones, and the action's place told to every patch
    assert (profile.data.pusht.action_repeat, profile.data.pusht.chunk) == (4, 1)
    assert profile.data.pusht.mix == (0.5, 0.25, 0.25) and profile.model.action_place == (0, 1)
  assert (h100.model.depth, h100.model.hidden_size, h100.batch_size) == (12, 384, 64)
  assert (h100.model.dtype, h100.train.num_steps) == ("bfloat16", 3000)
  assert h100.data.pusht == cpu.data.pusht == latent.data.pusht  # one dataset, prepared once
  # the cpu recipe in 12x12x8 latents of a codec fitted to the data: 1x1 patches (144 tokens)
  assert (latent.codec.kind, latent.codec.path, latent.data.latents_dir) == ("vae", "", "")
  assert (latent.frame_shape, latent.model.patch_size, latent.model.in_channels) == ((12, 12, 8), 1, 8)
  assert latent.diffusion.object_weight == 0.0 and not latent.sampling.clip_denoised
  assert latent.model.depth == cpu.model.depth
  assert latent.sampling.to_dict() == cpu.sampling.to_dict() | {"clip_denoised": False}
  assert load_config(str(ROOT / "configs" / "pusht.py")).to_dict() == cpu.to_dict()
  with pytest.raises(ValueError, match="profile must be one of"):
    load_config(str(ROOT / "configs" / "pusht.py:tpu"))


@pytest.mark.integration
def test_prepare_command_writes_labelled_episodes(tmp_path):
  assert cli.main(["data", "prepare", "pusht", "--data_dir", str(tmp_path),
                   "--train_episodes", "4", "--test_episodes", "2", "--episode_length", "6",
                   "--noise_levels", "0,0.5", "--batch", "3"]) == 0
  builder_dir = pusht_data.prepare(str(tmp_path), pusht_data.PushTConfig(
      train_episodes=4, test_episodes=2, episode_length=6, noise_levels=(0, 0.5), batch=3))
  source = ArrayRecordEpisodes(builder_dir, "train", "pusht")
  assert len(source) == 4
  noise = [float(source.episode(i).extras["policy_noise"][0]) for i in range(4)]
  assert sorted(noise) == [0.0, 0.0, 0.5, 0.5]  # levels cycle (TFDS shuffles the order)
  episode = source.episode(1)
  assert episode.actions.shape == (6, 2) and episode.extras["state"].shape == (6, 5)
  # the stored coverage is the simulator's for the stored state (gym-pusht's observation layout)
  agent_x, agent_y, x, y, angle = episode.extras["state"][-1].astype(np.float64)
  _, info = _render(pusht.reset_state((agent_x, agent_y), (x, y), angle)[None])
  assert episode.extras["coverage"][-1] == pytest.approx(info["coverage"][0], abs=0.02)
  assert episode.extras["success"].dtype == bool
  # the replayed start states are the ones written (TFDS shuffles the episodes; float32 on disk;
  # the stored state holds the block's body origin, a reset vector its centre of gravity)
  stored = np.stack([pusht.reset_state(s[:2], s[2:4], s[4]) for s in (
      source.episode(i).extras["state"][0].astype(np.float64) for i in range(4))])
  replayed = pusht_data.PushT.start_states(pusht_data.PushTConfig(
      train_episodes=4, test_episodes=2, episode_length=6, noise_levels=(0, 0.5), batch=3),
      "train")
  assert synthetic.matching(stored, replayed, atol=1e-3).all()


@pytest.mark.unit
def test_episode_mix_defaults_unchanged_and_kinds_interleaved():
  """The default mix is all scripted: the dataset's name, its start states and its noise levels
  are those written before the mix existed; a mix interleaves the kinds in their fractions and
  draws nothing from the start states' stream."""
  default = pusht_data.PushTConfig(train_episodes=640)
  assert default.mix == (1.0, 0.0, 0.0)
  assert default.name == "s48_l40_e640-64_n0-0.1-0.2-0.5_c4_o90_a0.5_seed0"
  old = pusht.random_initial_states(np.random.default_rng(0), 32, max_offset=90.0,
                                    max_angle=0.5)  # the first batch, drawn as before the mix
  np.testing.assert_array_equal(pusht_data.PushT.start_states(default, "train")[:32], old)
  kinds, noise, _, _ = next(pusht_data._draws(default, 8, np.random.default_rng(0)))
  assert (kinds == 0).all()
  np.testing.assert_allclose(noise, [0.0, 0.1, 0.2, 0.5] * 2)
  mixed = pusht_data.PushTConfig(train_episodes=640, mix=(0.5, 0.25, 0.25))
  assert mixed.name == default.name + "_m0.5-0.25-0.25_r160"
  np.testing.assert_array_equal(pusht_data.PushT.start_states(mixed, "train"),
                                pusht_data.PushT.start_states(default, "train"))
  kinds = synthetic.episode_kinds(mixed.mix, 640)
  assert np.bincount(kinds).tolist() == [320, 160, 160]
  assert all(abs((kinds[:n] == 1).sum() - n / 4) <= 1 for n in range(1, 641))
  kinds, noise, _, _ = next(pusht_data._draws(mixed, 8, np.random.default_rng(0)))
  np.testing.assert_allclose(noise[kinds == 0], [0.0, 0.1, 0.2, 0.5])  # cycling over pushes
  assert set(noise[kinds == 1]) == {pusht_data.RANDOM_AGENT}
  assert set(noise[kinds == 2]) == {pusht_data.IDLE_AGENT}
  with pytest.raises(ValueError, match="mix must be"):
    pusht_data.PushTConfig(mix=(0.5, 0.5))
  with pytest.raises(ValueError, match="mix must be"):
    pusht_data.PushTConfig(mix=(0.5, 0.25, 0.5))


@pytest.mark.unit
def test_episode_mix_idle_agents_keep_everything_still_and_random_agents_touch_the_t():
  """Idle episodes: neither the agent nor the T moves. Random agents move the agent, and touch
  the T in some episodes (it moves); scripted episodes are those of the all-scripted data."""
  mixed = pusht_data.PushTConfig(episode_length=25, batch=12, mix=(1 / 3, 1 / 3, 1 / 3))
  episodes = list(pusht_data.collect(mixed, 12, np.random.default_rng(3)))
  scripted = list(pusht_data.collect(dataclasses.replace(mixed, mix=(1.0, 0.0, 0.0)), 12,
                                     np.random.default_rng(3)))
  kinds = synthetic.episode_kinds(mixed.mix, 12)
  moved = {0: [], 1: [], 2: []}
  for kind, episode in zip(kinds, episodes):
    state = episode.observations["state"]
    agent = np.abs(state[:, :2] - state[0, :2]).max()
    block = np.abs(state[:, 2:] - state[0, 2:]).max()
    moved[kind].append((agent, block))
    if kind == 2:
      assert agent < 1e-3 and block < 1e-3
      assert (np.diff(episode.images.astype(int), axis=0) == 0).all()  # still frames
    if kind == 1:
      assert agent > 20.0
  assert max(block for _, block in moved[1]) > 5.0  # some random agent pushed the T
  # the first episode is scripted at noise 0 in both: the same pushes as in all-scripted data
  assert kinds[0] == 0 and episodes[0].observations["policy_noise"][0] == 0.0
  np.testing.assert_array_equal(episodes[0].observations["state"],
                                scripted[0].observations["state"])


@pytest.mark.unit
def test_collecting_in_worker_processes_gives_the_same_episodes_in_the_same_order():
  config = pusht_data.PushTConfig(image_size=16, episode_length=3, batch=2,
                                  mix=(0.5, 0.25, 0.25))
  serial = list(pusht_data.collect(config, 5, np.random.default_rng(5)))
  parallel = list(pusht_data.collect(config, 5, np.random.default_rng(5), workers=2))
  assert len(parallel) == 5
  for one, other in zip(serial, parallel, strict=True):
    np.testing.assert_array_equal(one.images, other.images)
    np.testing.assert_array_equal(one.actions, other.actions)
    for key, values in one.observations.items():
      np.testing.assert_array_equal(values, other.observations[key])
  with pytest.raises(ValueError, match="workers must be >= 1"):
    next(pusht_data.collect(config, 1, np.random.default_rng(5), workers=0))
  with pytest.raises(ValueError, match="workers must be >= 1"):
    pusht_data.prepare("/nonexistent/never-written", config, workers=0)


@pytest.mark.unit
def test_without_the_simulator_preparing_writes_nothing(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, "gym_pusht", None)  # its import fails, as when not installed
  with pytest.raises(ImportError, match=r"pip install 'wmjax\[pusht\]'"):
    pusht_data.prepare(str(tmp_path / "data"), pusht_data.PushTConfig(train_episodes=2))
  assert not (tmp_path / "data").exists()  # no dataset folder, no lock


@pytest.mark.unit
def test_reward_functions(tmp_path):
  states = np.stack([pusht.reset_state((60, 60), pusht.GOAL_POSE[:2], pusht.GOAL_POSE[2]),
                     pusht.reset_state((60, 60), (150, 380), 0.3)])
  frames, _ = _render(states)
  videos = np.stack([frames, frames[::-1]])  # [2 rollouts, 2 frames]
  np.testing.assert_allclose(coverage(videos), pusht.frame_coverage(
      to_model(frames[::-1])), rtol=1e-6)
  distance = rewards.GoalImageDistance(frames[0])(videos)
  assert distance[1] == 0.0 and distance[0] < -0.01
  with pytest.raises(ValueError, match="goal image must be"):
    rewards.GoalImageDistance(frames[0, :10])(videos)
  Image.fromarray(frames[0]).save(tmp_path / "goal.png")  # `--reward goal:PNG` of eval-policy
  np.testing.assert_allclose(rewards.reward_from_spec(f"goal:{tmp_path / 'goal.png'}")(videos),
                             distance)
  with pytest.raises(ValueError, match="reward must be"):
    rewards.reward_from_spec("iou")


@pytest.mark.slow
@pytest.mark.unit
def test_success_classifier_learns_and_round_trips(tmp_path):
  rng = np.random.default_rng(0)
  states = pusht.random_initial_states(rng, 48, max_offset=160, max_angle=1.0)
  frames, info = _render(states)
  labels = info["coverage"] > 0.3
  classifier, metrics = rewards.train_success_classifier(frames, labels, steps=150,
                                                         batch_size=32, label="coverage > 0.3")
  accuracy = ((classifier.probabilities(frames) > 0.5) == labels).mean()
  assert accuracy > 0.85, (accuracy, labels.mean(), metrics)
  loaded = rewards.SuccessClassifier.load(classifier.save(str(tmp_path / "clf")))
  np.testing.assert_allclose(loaded(frames[:, None]), classifier(frames[:, None]), atol=1e-6)
  assert loaded.label == "coverage > 0.3"
  with pytest.raises(ValueError, match="both classes"):
    rewards.train_success_classifier(frames, np.zeros(48, bool))


@pytest.fixture(scope="module")
def experiment(pusht_experiment, tmp_path_factory):
  """(run.py's main, its arguments) on a copy of the suite's Push-T experiment (conftest.py): the
  data, success classifier and tiny world model of the experiment script's first stages."""
  root = shutil.copytree(pusht_experiment, tmp_path_factory.mktemp("pusht") / "run")
  return pusht_experiment_script().main, ["--workdir", str(root)] + PUSHT_EXPERIMENT_TINY


def _check_summary(result: dict, plan: dict) -> None:
  """:func:`summarize` of a policy evaluation and a plan run of K = 1 and 3 (2 re-plannings)."""
  summary = summarize(result, plan)
  assert summary["ranking_matches"] in (True, False)
  assert set(summary["planning"]) == set(summary["planning_lookahead"]) == {"1", "3"}
  one, three = plan["candidates"]["1"]["world_model"], plan["candidates"]["3"]["world_model"]
  gains = np.subtract(three["per_episode"], one["per_episode"])
  assert summary["planning"]["3"]["gain_mean"] == pytest.approx(gains.mean())
  assert summary["planning"]["3"]["mean"] == pytest.approx(three["final_coverage"]["mean"])
  assert summary["planning"]["1"]["gain_mean"] == 0.0
  assert summary["held_out"] is True
  assert summary["block_iou_push_end"] == result["policies"]["push"]["block"]["world_model"][
      "end"]["block_iou"]
  for k in ("1", "3"):  # exploitability: K = 1's single candidate is imagined too
    row = plan["candidates"][k]["world_model"]
    # per episode, averaged over its 2 replannings: the standard error is clustered by episode
    assert row["imagined_value"]["rollouts"] == row["simulator_value"]["rollouts"] == 2
    assert summary["planning"][k]["exploitability_gap"] == pytest.approx(
        row["imagined_value"]["mean"] - row["simulator_value"]["mean"])
    assert "exploitability_gap" not in summary["planning_lookahead"][k]
  assert summary["planning"]["1"]["selection_effect"] == 0.0
  assert summary["planning"]["3"]["selection_effect"] == pytest.approx(
      summary["planning"]["3"]["exploitability_gap"] - summary["planning"]["1"]["exploitability_gap"])
  assert not summarize(result, {**plan, "held_out": None})["held_out"]
  json.dumps(summary, allow_nan=False)  # NaN correlations are None: strict JSON
  with pytest.raises(ValueError, match="over K = 1"):
    summarize(result, {**plan, "candidates": {"3": plan["candidates"]["3"]}})
  with pytest.raises(ValueError, match="was not evaluated"):
    summarize(result, plan, reward="vlm")


@pytest.mark.slow
@pytest.mark.integration
def test_experiment_script_runs_its_stages_resumably(experiment, capsys):
  """run.py's stages, resumable; its policy and plan stages are the `wmjax eval-policy` and
  `wmjax plan` commands end to end (--smoke: 4 episodes of 8 steps, planning 2 of 4, K 1 and 3),
  so their outputs are checked here too."""
  run, args = experiment
  root = Path(args[1])
  assert run(args + ["--minutes", "0"]) == 3  # the deadline has passed: nothing starts
  assert not (root / "policy_eval").exists()
  with pytest.raises(SystemExit, match=r"lacks policy_eval/policy_eval.json \(stage policy\), "
                                       r"plan/plan.json \(stage plan\): run those stages first"):
    run(args + ["--stage", "summary"])
  assert run(args) == 0  # data, classifier and model done before: skipped
  result = json.loads((root / "policy_eval" / "policy_eval.json").read_text())
  classifier = f"classifier:{root / 'classifier'}"
  assert list(result["policies"]) == ["push", "push@0.1", "push@0.2", "push@0.5", "stay"]
  assert result["held_out"] is True
  for values in result["policies"].values():
    assert set(values) == {"simulator", "block", "coverage", classifier}
    assert 0.0 <= values["simulator"]["mean"] <= 1.0
    assert values["simulator"]["mean"] == pytest.approx(np.mean(values["simulator"]["per_episode"]))
    assert values["coverage"]["world_model"]["rollouts"] == 4
    assert len(values["coverage"]["world_model"]["per_episode"]) == 4
    for kind in ("world_model", "copy_first_frame"):
      per_step = values["block"][kind]["per_step"]
      assert {m: len(v) for m, v in per_step.items()} == {
          "block_error_px": 8, "block_angle_error_deg": 8, "block_iou": 8}
      assert values["block"][kind]["end"]["block_iou"] == per_step["block_iou"][-1]
      episodes = values["block"][kind]["end_per_episode"]["block_iou"]
      assert len(episodes) == 4 and np.mean(episodes) == pytest.approx(per_step["block_iou"][-1])
  intervals = result["rewards"]["coverage"]["agreement_ci95"]
  assert intervals["samples"] == 2000 and intervals["level"] == 0.95
  pearson = result["rewards"]["coverage"]["agreement"]["pearson"]
  assert pearson is None or np.isnan(pearson) or -1.0 <= pearson <= 1.0
  report = (root / "policy_eval" / "policy_eval.md").read_text()
  assert "## Reward: coverage" in report and "| push |" in report
  assert "held out from the training split: True" in report and "The T at the last step" in report
  plan = json.loads((root / "plan" / "plan.json").read_text())  # the K runs merged
  assert set(plan["candidates"]) == {"1", "3"} and plan["held_out"] is True
  # 4 steps, one executed per plan (the profile acts one held action at a time: chunk 1)
  assert plan["candidates"]["3"]["world_model"]["replans"] == 4
  assert set(plan["candidates"]["1"]) == {"world_model", "simulator"}  # --lookahead
  assert "| 3 |" in capsys.readouterr().out
  _check_summary(result, plan)
  summary = json.loads((root / "summary.json").read_text())
  assert (summary["profile"], summary["train_steps"]) == ("cpu", 2)
  assert summary["minutes"] == pytest.approx(sum(summary["stage_minutes"].values()), abs=0.05)
  # the stages before the summary (its own few milliseconds are added after it is written)
  assert set(summary["stage_minutes"]) == {"data", "classifier", "codec", "train", "policy", "plan"}
  assert "codec_held_out" not in summary  # a pixel profile fits no codec
  assert set(summary["planning"]) == set(summary["planning_lookahead"]) == {"1", "3"}
  assert set(summary["policies"]) == {"push", "push@0.1", "push@0.2", "push@0.5", "stay"}
  assert summary["held_out"] is True and 0.0 <= summary["block_iou_push_end"] <= 1.0
  for name in ("pearson_ci95", "spearman_ci95"):  # [lo, hi], or None if never defined
    assert summary[name] is None or -1.0 <= summary[name][0] <= summary[name][1] <= 1.0
  for k in ("1", "3"):
    assert plan["candidates"][k] == json.loads(
        (root / "plan" / f"K{k}" / "plan.json").read_text())["candidates"][k]
  assert (root / "policy_eval" / "videos" / "stay.gif").exists()
  (root / "summary.json").unlink()  # every stage is found done; the summary is the same
  assert run(args + ["--stage", "train", "--stage", "plan", "--stage", "summary"]) == 0
  again = json.loads((root / "summary.json").read_text())
  assert again["minutes"] >= summary["minutes"]  # wall time adds up over the runs
  timing = ("minutes", "stage_minutes")
  assert {k: v for k, v in again.items() if k not in timing} == {
      k: v for k, v in summary.items() if k not in timing}
  (root / "summary.json").unlink()  # past the deadline the milliseconds' summary still runs
  assert run(args + ["--minutes", "0", "--stage", "summary"]) == 0
  assert (root / "summary.json").exists()
  with pytest.raises(SystemExit):
    run(args + ["--config.train.num_stepz=3"])


@pytest.mark.slow
@pytest.mark.integration
def test_h100_profile_trains_one_step(experiment, tmp_path):
  """The h100 profile (bfloat16, the attention the platform offers) at tiny widths, one step on
  the experiment's data."""
  data = [a for a in PUSHT_EXPERIMENT_TINY if a.startswith(("--config.data.pusht", "--config.frame"))]
  tiny = {"data.data_dir": os.path.join(experiment[1][1], "data"), "data.num_workers": 0,
          "model.depth": 2, "model.hidden_size": 32, "model.num_heads": 2, "batch_size": 8,
          "train.num_steps": 1, "train.eval_every": 0}
  assert cli.main(["train", "--config", str(ROOT / "configs" / "pusht.py:h100"), "--workdir",
                   str(tmp_path)] + data + [f"--config.{k}={v!r}" for k, v in tiny.items()]) == 0
  saved = json.loads((tmp_path / "config.json").read_text())
  assert (saved["name"], saved["model"]["dtype"]) == ("pusht-h100", "bfloat16")
  assert json.loads((tmp_path / "metrics.json").read_text()) == {"step": 1}


@pytest.mark.slow
@pytest.mark.integration
def test_latent_profile_fits_a_codec_to_its_data_and_trains_on_its_latents(pusht_experiment,
                                                                           tmp_path, capsys):
  """run.py --profile latent: the codec stage fits a codec to the run's frames (4x smaller sides)
  and encodes the data with it; training reads those latents through the codec the stage wrote;
  a second run finds both done and changes nothing."""
  shutil.copytree(pusht_experiment / "data", tmp_path / "data")
  tiny = [a for a in PUSHT_EXPERIMENT_TINY if not a.startswith("--config.frame_shape")]
  args = (["--workdir", str(tmp_path), "--profile", "latent", "--stage", "codec", "--stage", "train",
           "--config.frame_shape=(4,4,8)", "--config.train.auto_fit=False"] + tiny)
  run = pusht_experiment_script().main
  assert run(args) == 0
  report = json.loads((tmp_path / "codec" / "wmjax_codec.json").read_text())
  # the codec's latents are the config's frame_shape: 4x smaller sides, its channels
  assert report["latent_shape"] == [4, 4, 8] and report["recipe"]["widths"] == [16, 32, 64]
  assert not (tmp_path / "codec.incomplete").exists()
  latents = json.loads((tmp_path / "latents" / "wmjax_latents.json").read_text())
  assert latents["latent_shape"] == [4, 4, 8] and set(latents["splits"]) == {"train", "test"}
  saved = json.loads((tmp_path / "model" / "config.json").read_text())
  assert (saved["name"], saved["codec"]["kind"]) == ("pusht-latent", "vae")
  assert saved["codec"]["path"] == str(tmp_path / "codec")
  assert saved["data"]["latents_dir"] == str(tmp_path / "latents")
  assert json.loads((tmp_path / "model" / "metrics.json").read_text()) == {"step": 2}
  weights = (tmp_path / "codec" / "diffusion_pytorch_model.safetensors").read_bytes()
  capsys.readouterr()
  assert run(args) == 0
  assert capsys.readouterr().out.count("done before") == 3  # codec, latents, model
  assert (tmp_path / "codec" / "diffusion_pytorch_model.safetensors").read_bytes() == weights


@pytest.mark.slow
@pytest.mark.integration
def test_push_task_improves_a_cloned_policy_in_the_world_model_checked_in_gym_pusht(
    pusht_experiment):
  """The ``push`` control task of a Push-T world model: held-out start states, the world model's
  episodes starting from the simulator's context frames and still actions, and one round of
  improvement in imagination checked in gym-pusht."""
  from wmjax import registry
  from wmjax.model import load_model
  from wmjax.train.improve import ImproveSettings, improve_on_task, world_model_rollout
  from wmjax.train.policy import clone_policy

  model = load_model(str(pusht_experiment / "model"))
  task = registry.control_task("push", model.config)
  c = model.config.rollout.context
  assert (task.context, task.steps) == (c, 32 // model.config.data.pusht.action_repeat)
  evaluation = task.start_states(3, "evaluate")
  learning = task.start_states(4, "plan", exclude=evaluation)
  assert task.held_out(evaluation) and task.held_out(learning)
  assert not synthetic.matching(learning, evaluation).any()
  frames, still = task.start(evaluation)
  assert frames.shape == (3, c) + model.image_shape and frames.dtype == np.uint8
  assert still.shape == (3, c - 1, 2)
  train_split = open_dataset(model.config.data).split("train")
  stored_noise = np.array([train_split.episode(i, 0, 1).extras["policy_noise"][0]
                           for i in range(len(train_split))])
  np.testing.assert_array_equal(np.sort(stored_noise),  # the split's order is the writer's
                                np.sort(task.world.episode_noise(len(train_split))))
  kept = [task.demonstration(train_split.episode(i, 0, 1)) for i in range(len(train_split))]
  np.testing.assert_array_equal(kept, stored_noise > 0)
  assert 0 < sum(kept) < len(kept)  # the noisy pushes, not the others
  policy, _ = clone_policy(model, task.controls, steps=2, batch_size=4, keep=task.demonstration)
  key = jax.random.key(0)
  imagined = world_model_rollout(model, task, evaluation)(policy, key)
  np.testing.assert_allclose(np.asarray(imagined["frames"])[:, :c], to_model(frames), atol=1e-6)
  true = task.run(policy, evaluation, key)
  assert true["frames"].shape == (3, c + task.steps) + model.image_shape
  assert true["actions"].shape == (3, task.steps, 2)
  np.testing.assert_array_equal(task.reward(true["frames"]), coverage(true["frames"]))
  settings = ImproveSettings(rounds=1, rollouts=4, fit_steps=2, batch_size=4, keep=0.5)
  _, report = improve_on_task(model, policy, task, settings, evaluation_states=3)
  assert report["held_out"] is True and [r["round"] for r in report["rounds"]] == [0, 1]
  for record in report["rounds"]:
    assert 0.0 <= record["true_value"] <= 1.0 and 0.0 <= record["imagined_value"] <= 1.0
    assert record["gap"] == pytest.approx(record["imagined_value"] - record["true_value"])


@pytest.mark.unit
def test_planner_scores_tell_sampling_noise_from_model_error():
  """``experiments/pusht/planner_scores.py``'s analysis: a model whose scores are the truth plus
  sampling noise over-values its choice on the sample it chose on but not on fresh samples, and
  averaging its samples lifts the validity; a model with a fixed error per candidate over-values
  its choice on fresh samples as much."""
  module = pusht_experiment_script("planner_scores")
  rng = np.random.default_rng(0)
  decisions, k, s = 400, 10, 3
  true = rng.normal(size=(decisions, k))
  episodes = np.arange(decisions) // 4
  noisy = module.analyse(true[..., None] + rng.normal(size=(decisions, k, s)), true, episodes)
  assert noisy["reliability"] == pytest.approx(0.5, abs=0.05)
  assert noisy["validity"]["mean_of_samples"] > noisy["validity"]["one_sample"] + 0.1
  assert noisy["overvalued"]["chosen_sample"]["mean"] > 0.5
  assert abs(noisy["overvalued"]["fresh_sample"]["mean"]) < 0.1
  assert noisy["mean_of_samples_minus_one_sample"]["mean"] > 0
  wrong = true + rng.normal(size=(decisions, k))  # the same error on every sample
  biased = module.analyse(np.repeat(wrong[..., None], s, -1), true, episodes)
  assert biased["reliability"] == pytest.approx(1.0)
  chosen, fresh = biased["overvalued"]["chosen_sample"], biased["overvalued"]["fresh_sample"]
  assert fresh["mean"] == pytest.approx(chosen["mean"]) and fresh["mean"] > 0.5
  assert biased["gain"]["oracle"]["mean"] > biased["gain"]["one_sample"]["mean"] > 0


@pytest.mark.unit
def test_planner_scores_ensemble_corrects_only_independent_errors():
  """``planner_scores.py --combine``: two models whose errors are independent choose better by
  their sum than one model by two samples; two models with the same error gain nothing from it."""
  module = pusht_experiment_script("planner_scores")
  rng = np.random.default_rng(1)
  decisions, k, s = 400, 10, 3
  true = rng.normal(size=(decisions, k))
  episodes = np.arange(decisions) // 4

  def model(error):
    return (true + error)[..., None] + 0.1 * rng.normal(size=(decisions, k, s))

  independent = module.analyse_ensemble(model(rng.normal(size=true.shape)),
                                        model(rng.normal(size=true.shape)), true, episodes)
  assert abs(independent["error_correlation"]) < 0.15
  assert independent["slope"] == pytest.approx([1.0, 1.0], abs=0.1)
  assert independent["validity"]["ensemble"] > independent["validity"]["two_samples_one_model"] + 0.1
  assert independent["ensemble_minus_two_samples_one_model"]["mean"] > 0.1
  shared = rng.normal(size=true.shape)
  same = module.analyse_ensemble(model(shared), model(shared), true, episodes)
  assert same["error_correlation"] > 0.95
  assert abs(same["ensemble_minus_two_samples_one_model"]["mean"]) < 0.05
  with pytest.raises(ValueError, match="share one shape"):
    module.analyse_ensemble(model(shared), model(shared)[:, :5], true, episodes)


@pytest.mark.unit
def test_contact_from_state_frames_each_transition_in_the_t_frame_and_scores_by_motion():
  """``experiments/pusht/contact_from_state.py``: a transition's targets, drawn in the T's frame
  at ``t``, give back the true next pose; inputs do not change when the whole scene turns and
  moves; copying scores IoU 1 on a still T and below on a pushed one; the MLP fits a rule."""
  module = pusht_experiment_script("contact_from_state")
  rng = np.random.default_rng(0)
  states = rng.uniform(100, 400, size=(6, 5, 5))
  states[..., 4] = rng.uniform(-np.pi, np.pi, size=(6, 5))
  states[:3, :, 2:] = states[:3, :1, 2:]  # episodes 0-2: a T that never moves
  actions = rng.uniform(100, 400, size=(6, 5, 2))
  data = module.transitions(states, actions)
  assert data["inputs"].shape == (18, 12) and data["targets"].shape == (18, 3)
  back = module.poses_from(data["targets"], data["now"])
  np.testing.assert_allclose(back[:, :2], data["next"][:, :2], atol=1e-3)
  np.testing.assert_allclose(np.exp(1j * back[:, 2]), np.exp(1j * data["next"][:, 2]), atol=1e-5)
  turn, shift = 0.7, np.array([13.0, -21.0])

  def moved(xy):  # the whole scene turned by ``turn`` about the origin and shifted
    return np.stack([np.cos(turn) * xy[..., 0] - np.sin(turn) * xy[..., 1],
                     np.sin(turn) * xy[..., 0] + np.cos(turn) * xy[..., 1]], -1) + shift

  scene = np.concatenate([moved(states[..., :2]), moved(states[..., 2:4]),
                          states[..., 4:] + turn], -1)
  np.testing.assert_allclose(module.transitions(scene, moved(actions))["inputs"], data["inputs"],
                             atol=1e-4)
  copy = module.score(data["now"], data, 48)
  assert copy["still"]["block_iou"]["mean"] == 1.0
  assert copy["pushed"]["block_iou"]["mean"] < 0.5
  predict = module.fit(data["inputs"], data["targets"], steps=300, batch=18, seed=0)
  fitted = module.score(module.poses_from(predict(data["inputs"]), data["now"]), data, 48)
  assert fitted["pushed"]["block_iou"]["mean"] > copy["pushed"]["block_iou"]["mean"]
  steps = iter(range(3))  # a predictor that knows each step's true move rolls out the truth
  exact = module.roll_out(lambda _: data["targets"].reshape(6, 3, 3)[:, next(steps)], states,
                          actions)
  np.testing.assert_allclose(exact[..., :2], states[:, 2:, 2:4], atol=1e-3)
  np.testing.assert_allclose(np.exp(1j * exact[..., 2]), np.exp(1j * states[:, 2:, 4]), atol=1e-5)
  end = module.rollout_end(exact[:, -1], states, 48)
  assert end["all"]["mean"] == pytest.approx(1.0) and end["moved"]["episodes"] == 3


@pytest.mark.unit
def test_contact_from_state_reads_the_state_back_from_frames():
  """``contact_from_state.seen_states``: the agent's and the T's poses read from 96-pixel frames
  drawn from known states come back within a few simulator units and degrees."""
  from wmjax.tasks.pusht.simulator import PALETTE, goal_mask
  module = pusht_experiment_script("contact_from_state")
  states = np.array([[[120.0, 380.0, 250.0, 240.0, 0.3], [400.0, 100.0, 230.0, 280.0, -1.2]]])
  size = 96
  frames = np.full((1, 2, size, size, 3), 255, np.uint8)
  centres = (np.arange(size) + 0.5) * 512.0 / size
  for t, state in enumerate(states[0]):
    frames[0, t][goal_mask(size, state[2:])] = PALETTE[2]
    disc = np.hypot(centres[None, :] - state[0], centres[:, None] - state[1]) <= 15.0
    frames[0, t][disc] = PALETTE[3]
  seen = module.seen_states(frames)
  np.testing.assert_allclose(seen[..., :4], states[..., :4], atol=4.0)
  np.testing.assert_allclose(np.degrees(np.angle(np.exp(1j * (seen[..., 4] - states[..., 4])))), 0,
                             atol=3.0)
  data = module.transitions(np.repeat(states, 3, 1), np.zeros((1, 6, 2)), np.repeat(seen, 3, 1))
  np.testing.assert_allclose(data["now"], np.repeat(seen, 3, 1)[0, 1:5, 2:])
  np.testing.assert_allclose(data["moved"], [0.0, np.hypot(20.0, 40.0), 0.0, 0.0], atol=1e-9)


@pytest.mark.integration
def test_contact_from_state_closed_loop_with_exact_predictions_replays_the_simulator():
  """``contact_from_state.closed_loop``: with predictors that return the simulator's own next
  poses, the states it draws show the policy what the simulator's frames show, so the policy
  (noisy, with eval-policy's keys) takes the simulator's actions and the episode comes back."""
  import jax

  from wmjax.tasks.pusht.simulator import PushPolicy, random_initial_states, simulate_policy
  module = pusht_experiment_script("contact_from_state")
  policy, key = PushPolicy(noise=0.1), jax.random.key(3)
  starts = random_initial_states(np.random.default_rng(5), 3)
  truth = simulate_policy(policy, starts, 4, image_size=48, key=key, context=2, action_repeat=4)
  states, actions = truth["state"].astype(np.float64), truth["actions"].astype(np.float64)
  data = module.transitions(states, actions)
  block, agent = (v.reshape(3, 4, -1) for v in (data["targets"],
                                                 module.agent_targets(states)))
  inputs = data["inputs"].reshape(3, 4, -1)
  calls = {"block": 0, "agent": 0}

  def oracle(name, targets):
    def predict(x):
      step = calls[name]
      calls[name] += 1
      np.testing.assert_allclose(x, inputs[:, step], atol=1e-3)  # the simulator's actions too
      return targets[:, step]
    return predict

  replayed = module.closed_loop(oracle("block", block), oracle("agent", agent), policy,
                                states[:, :2], actions, 4, key, image_size=48, action_repeat=4)
  np.testing.assert_allclose(replayed, states, atol=1e-2)
  assert calls == {"block": 4, "agent": 4}


@pytest.mark.integration
def test_plan_with_learner_imagines_each_candidate_from_the_state_it_reads(monkeypatch):
  """``experiments/pusht/plan_with_learner.py``: a learner that keeps the T and the agent where
  they are imagines, for every candidate, the frame the simulator shows now; one that moves the
  T draws it elsewhere."""
  from wmjax.tasks.pusht.simulator import PushTSimulator, random_initial_states
  monkeypatch.syspath_prepend(str(ROOT / "experiments" / "pusht"))
  module = pusht_experiment_script("plan_with_learner")
  sim = PushTSimulator(2, 48, 4)
  frames, actions, infos = sim.start(random_initial_states(np.random.default_rng(1), 2), 2)
  frames, history = np.stack(frames, 1), np.stack([i["state"] for i in infos], 1)

  def planner(block_move):
    return module.LearnerLookahead(lambda x: np.tile(block_move, (len(x), 1)),
                                   lambda x: x[:, 2:4],  # the agent's place now, in the T's frame
                                   lambda window: history.astype(np.float64), None, None, 3, 1,
                                   48, 4)

  candidates = np.random.default_rng(2).uniform(100, 400, (2, 3, 1, 2))
  still = planner(np.zeros(3)).imagine(frames, np.stack(actions, 1), candidates, None)
  assert still.shape == (2, 3, 3, 48, 48, 3)
  np.testing.assert_array_equal(still[:, :, :2], np.repeat(frames[:, None], 3, 1))
  np.testing.assert_array_equal(still[:, :, 2], np.repeat(frames[:, None, 1], 3, 1))
  moved = planner(np.array([5.0, 0.0, 0.0])).imagine(frames, np.stack(actions, 1), candidates,
                                                     None)
  assert (moved[:, :, 2] != frames[:, None, 1]).any(axis=(2, 3, 4)).all()


@pytest.mark.unit
def test_probe_split_by_motion_measures_the_t_move_into_the_first_generated_frame():
  """``experiments/pusht/probe.py --split_by_motion``: the T's move and turn from the last context frame into
  the first generated one, and copying the last context frame's T IoU there (1 for a still T,
  low for a pushed one)."""
  from types import SimpleNamespace

  from wmjax.tasks.pusht.simulator import PALETTE, goal_mask
  module = pusht_experiment_script("probe")
  poses = [[(200.0, 200.0, 0.0)] * 3, [(200.0, 200.0, 0.0), (200.0, 200.0, 0.0),
                                       (240.0, 230.0, np.pi / 6)]]
  frames = np.full((2, 3, 48, 48, 3), 255, np.uint8)
  state = np.zeros((2, 3, 5), np.float32)
  for w, window in enumerate(poses):
    for t, pose in enumerate(window):
      frames[w, t][goal_mask(48, pose)] = PALETTE[2]  # the block's colour
      state[w, t, 2:] = pose
  shift, turn, copy = module.first_frame_moves(SimpleNamespace(frames=frames,
                                                               extras={"state": state}))
  np.testing.assert_allclose(shift, [0.0, 50.0], atol=1e-4)
  np.testing.assert_allclose(turn, [0.0, 30.0], atol=1e-3)
  assert copy[0] == 1.0 and copy[1] < 0.5


def _evaluation(iou, angle, imagined, simulator, seed=0):
  """A ``wmjax eval-policy`` result of one policy, ``push``, with these per-episode values."""
  coverage = {"agreement": {"pearson": 0.9, "spearman": 1.0},
              "agreement_ci95": {"pearson": [0.5, 0.99]}}
  block = {"world_model": {"end_per_episode": {"block_iou": iou, "block_angle_error_deg": angle}}}
  return {"seed": seed, "rewards": {"coverage": coverage},
          "policies": {"push": {"block": block, "coverage": {
              "world_model": {"per_episode": imagined},
              "simulator_reward": {"per_episode": simulator}}}}}


@pytest.mark.unit
def test_paired_comparison_differences_episode_by_episode_and_refuses_other_start_states():
  """``experiments/pusht/paired.py``: the T's IoU and angle error of A less B per episode (an
  episode where either drew no T has no angle and is left out), and each model's imagined value
  less the simulator's."""
  module = pusht_experiment_script("paired")
  a = _evaluation([0.5, 0.7, 0.6], [10.0, float("nan"), 30.0], [0.4, 0.4, 0.4], [0.1, 0.2, 0.3])
  b = _evaluation([0.4, 0.4, 0.4], [20.0, 50.0, 60.0], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3])
  row = module.paired_table(a, b).splitlines()[-1].split(" | ")
  assert row[0] == "| push" and row[1] == "0.600 / 0.400"
  assert row[2] == "+0.200 ± 0.058"  # differences 0.1, 0.3, 0.2
  assert row[4] == "-20.0 ± 10.0"  # episodes 1 and 3 only: -10 and -30
  assert row[5] == "+0.200 ± 0.058" and row[6].startswith("+0.000 ± 0.000")
  with pytest.raises(ValueError, match="start states"):
    module.paired_table(a, _evaluation([0.4] * 3, [1.0] * 3, [0.1] * 3, [0.1] * 3, seed=1))


@pytest.mark.unit
def test_lost_pixels_tells_a_fading_outline_from_a_moved_t():
  """``experiments/pusht/lost_pixels.py``: a T whose outline is painted lighter loses exactly its
  outline pixels, to the light grey class, and keeps its interior; a moved T loses pixels to the
  background and adds as many over it."""
  from wmjax.tasks.pusht.simulator import PALETTE, goal_mask
  module = pusht_experiment_script("lost_pixels")
  truth = np.full((1, 48, 48, 3), 255, np.uint8)
  t_mask = goal_mask(48, (250.0, 250.0, 0.3))
  truth[0][t_mask] = PALETTE[2]
  faded = truth.copy()
  outline = module._outline(t_mask[None])[0]
  faded[0][outline] = (190, 195, 200)  # nearer the light grey than the T's colour
  report = module.frame_report(truth, faded)
  assert report["lost_as"]["wall"] == outline.sum() == report["true_pixels"] - report["model_pixels"]
  assert sum(report["added_over"].values()) == 0 and 0 < report["block_iou"] < 1
  assert report["interior_rgb"]["model"] == report["interior_rgb"]["simulator"]
  moved = np.full_like(truth, 255)
  moved[0][goal_mask(48, (330.0, 250.0, 0.3))] = PALETTE[2]
  report = module.frame_report(truth, moved)
  assert report["lost_as"]["background"] > 0 and report["added_over"]["background"] > 0
