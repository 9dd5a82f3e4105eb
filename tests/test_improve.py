"""Learnable policies and their improvement: the true gridworld (batched JAX and gymnasium) against
the dataset's own simulation, the reach task's held-out start states and frame reward, the policy
pytree (normalisation, controls, saving, one compiled rollout for new parameters), the weighting
and decisions of a round, and the two commands on a trained model."""

import json

import jax
import numpy as np
import pytest

from wmjax import cli
from wmjax.data import synthetic
from wmjax.data.stats import ActionStats
from wmjax.policy import LearnedPolicy, load_policy
from wmjax.tasks.gridworld import env
from wmjax.tasks.gridworld.dataset import Gridworld, GridworldConfig, render, simulate
from wmjax.tasks.gridworld.reach import ReachTask
from wmjax.train.improve import ImproveSettings, decisions, episode_weights

WORLD = GridworldConfig()


def _policy(controls=None, seed=0, chunk=1):
  rng = np.random.default_rng(0)
  stats = ActionStats.compute(rng.uniform(-2, 2, (1000, 4)), "gridworld", gripper_dim=None)
  return LearnedPolicy.create(stats, "mean_std", context=1, chunk=chunk, frame_shape=(16, 16, 3),
                              key=jax.random.key(seed), controls=controls, channels=(8, 8),
                              hidden=16)


@pytest.mark.unit
@pytest.mark.parametrize("snap", [True, False])
def test_true_gridworld_steps_and_renders_as_the_dataset_simulates(snap):
  world = GridworldConfig(snap_to_pixels=snap, episode_length=12)
  centres, actions = simulate(world, np.random.default_rng(3))
  stepped = [centres[0]]
  for a in actions[:-1]:
    stepped.append(np.asarray(env.step(world, stepped[-1], a)))
  np.testing.assert_array_equal(np.stack(stepped), centres)
  np.testing.assert_array_equal(np.asarray(env.render(world, centres)),
                                np.stack([render(c, world) for c in centres]))


@pytest.mark.unit
def test_reach_start_states_are_held_out_and_its_reward_reads_the_true_distance():
  task = ReachTask(WORLD)
  evaluation = task.start_states(64, "evaluate")
  imagination = task.start_states(512, "plan", exclude=evaluation)
  assert task.held_out(evaluation) and task.held_out(imagination)
  assert not synthetic.matching(evaluation, imagination).any()
  assert synthetic.matching(evaluation, task.start_states(512, "plan")).any()  # else by chance
  training = Gridworld.start_states(WORLD, "train")
  assert not task.held_out(training[:8])  # the check sees a training state
  assert (np.abs(evaluation[:, 1] - evaluation[:, 0]).max(-1) >= task.min_separation).all()
  # a policy that moves green straight at red: the reward read from frames is the true distance
  toward = lambda frames, key: np.zeros((len(frames), 1, 4), np.float32)  # noqa: E731
  out = task.run(toward, evaluation[:8], jax.random.key(0))
  true = np.linalg.norm(np.asarray(out["centres"])[:, -1, 1] - evaluation[:8, 0], axis=-1)
  np.testing.assert_allclose(-task.reward(out["frames"]), true, atol=1e-5)
  on_top = evaluation[:8].copy()
  on_top[:, 1] = on_top[:, 0]
  reached = np.concatenate([task.frames(evaluation[:8]), task.frames(on_top)], 1)
  assert task.success(reached).all() and not task.success(out["frames"]).any()
  assert (task.distance(task.frames(on_top)) == 16).all()  # red hidden at the start: no episode


@pytest.mark.unit
def test_gymnasium_gridworld_follows_the_batched_environment():
  from wmjax.tasks.gridworld.gym_env import GridworldEnv
  task = ReachTask(WORLD)
  gym = GridworldEnv(task)
  start = task.start_states(1, "evaluate")
  frame, info = gym.reset(options={"centres": start[0]})
  np.testing.assert_array_equal(frame, task.frames(start)[0, 0])
  actions = np.random.default_rng(0).uniform(-2, 2, (task.steps, 4)).astype(np.float32)
  steps = 0
  for a in actions:
    frame, reward, terminated, truncated, info = gym.step(a)
    steps += 1
    if terminated:
      break
  assert info["centres"][0].tolist() == start[0, 0].tolist()  # red stays: not controlled
  assert reward == pytest.approx(-np.linalg.norm(info["centres"][1] - start[0, 0]))
  assert truncated == (not terminated and steps == task.steps)
  with pytest.raises(ValueError, match=r"action must be \(4,\)"):
    gym.step(np.zeros(3))


@pytest.mark.unit
def test_action_affine_inverts_every_normalisation():
  rng = np.random.default_rng(0)
  raw = rng.normal(1.0, 3.0, (200, 3))
  for gripper in (None, 2):
    stats = ActionStats.compute(raw, "toy", gripper_dim=gripper)
    for mode in ("mean_std", "bounds", "none"):
      shift, scale = stats.affine(mode)
      inside = np.clip(raw, stats.p01, stats.p99)  # bounds clips outside [p01, p99]
      np.testing.assert_allclose(shift + scale * stats.normalize(inside, mode), inside,
                                 rtol=1e-5, atol=1e-5)


@pytest.mark.unit
def test_learned_policy_sets_only_its_controls_clips_to_the_data_and_round_trips(tmp_path):
  policy = _policy(controls=(False, False, True, True))
  frames = np.random.default_rng(0).uniform(-1, 1, (5, 1, 16, 16, 3)).astype(np.float32)
  noisy = policy.with_temperature(50.0)(frames, jax.random.key(1))
  assert noisy.shape == (5, 1, 4)
  assert (np.asarray(noisy)[..., :2] == 0).all()
  assert (np.asarray(noisy)[..., 2:] <= np.asarray(policy.high)[2:] + 1e-6).all()
  assert (np.asarray(noisy)[..., 2:] >= np.asarray(policy.low)[2:] - 1e-6).all()
  policy.save(str(tmp_path / "p"), info={"trained_by": "nothing"})
  again = load_policy(str(tmp_path / "p"))
  np.testing.assert_array_equal(again(frames, jax.random.key(1)), policy(frames, jax.random.key(1)))
  assert again.controls == policy.controls and again.context == 1
  from wmjax.tasks.pusht.simulator import policy_from_spec
  named = policy_from_spec(f"learned:{tmp_path / 'p'}", chunk=4)  # eval-policy --policy learned:DIR
  np.testing.assert_array_equal(named(frames, jax.random.key(1)), again(frames, jax.random.key(1)))
  with pytest.raises(FileExistsError, match="new directory"):
    policy.save(str(tmp_path / "p"))
  with pytest.raises(ValueError, match=r"reads \[B, 1, H, W, 3\] frames"):
    policy(np.zeros((5, 2, 16, 16, 3), np.float32), jax.random.key(0))


@pytest.mark.unit
def test_new_parameters_reuse_the_compiled_rollout():
  task = ReachTask(WORLD)
  states = task.start_states(4, "plan")
  first, second = _policy(seed=0), _policy(seed=1).with_temperature(1.0)
  second = second.replace(params=jax.tree.map(lambda p: p + 0.5, second.params))
  task.run(first.with_temperature(1.0), states, jax.random.key(0))
  misses = env._run_fn.cache_info().misses
  a = task.run(first.with_temperature(1.0), states, jax.random.key(0))["actions"]
  b = task.run(second, states, jax.random.key(0))["actions"]
  assert env._run_fn.cache_info().misses == misses
  assert not np.allclose(a, b)


@pytest.mark.unit
def test_rounds_keep_the_best_episodes_and_cut_them_into_decisions():
  returns = np.array([-3.0, -1.0, np.nan, -2.0, -0.5, -4.0, -6.0, -5.0, -7.0, -8.0])
  keep = episode_weights(returns, ImproveSettings(keep=0.2))
  assert keep.tolist() == [0, 1, 0, 0, 1, 0, 0, 0, 0, 0]
  rwr = episode_weights(returns, ImproveSettings(weighting="rwr", beta=1.0))
  assert rwr[4] == 1.0 and rwr[2] == 0 and rwr[1] == pytest.approx(np.exp(-0.5))
  with pytest.raises(ValueError, match="weighting must be one of"):
    ImproveSettings(weighting="best")
  # groups of 5 (one start state each) keep the best of each, though the second group's best
  # (-4) is worse than all but one of the first group's
  grouped = episode_weights(returns, ImproveSettings(rollouts=10, group=5, keep=0.2))
  assert grouped.tolist() == [0, 0, 0, 0, 1, 1, 0, 0, 0, 0]
  with pytest.raises(ValueError, match="divide rollouts"):
    ImproveSettings(rollouts=10, group=3)
  policy = _policy(chunk=2)
  frames = np.arange(3 * 6).reshape(3, 6, 1, 1, 1) * np.ones((1, 1, 16, 16, 3))
  actions = np.arange(3 * 5 * 4, dtype=np.float32).reshape(3, 5, 4)
  seen, chunks, episode = decisions({"frames": frames, "actions": actions}, policy)
  assert seen.shape == (6, 1, 16, 16, 3) and chunks.shape == (6, 2, 4)
  assert episode.tolist() == [0, 0, 1, 1, 2, 2]
  assert seen[3, 0, 0, 0, 0] == 6 + 2  # episode 1's second decision saw its frame 2
  np.testing.assert_allclose(chunks[3] * np.asarray(policy.scale) + np.asarray(policy.shift),
                             actions[1, 2:4], rtol=1e-5, atol=1e-4)


@pytest.mark.integration
@pytest.mark.slow
def test_clone_and_improve_commands_write_a_policy_and_a_checked_report(trained_workdir,
                                                                        tmp_path, capsys):
  start, better = str(tmp_path / "start"), str(tmp_path / "better")
  assert cli.main(["clone-policy", "--workdir", str(trained_workdir), "--out", start,
                   "--steps", "3", "--batch_size", "4"]) == 0
  assert json.loads((tmp_path / "start" / "policy.json").read_text())["controls"] == [
      False, False, True, True]
  assert cli.main(["improve", "--workdir", str(trained_workdir), "--policy", start, "--out",
                   better, "--rounds", "1", "--rollouts", "4", "--fit_steps", "2",
                   "--evaluation_states", "4", "--keep", "0.5"]) == 0  # one batch shape
  report = json.loads((tmp_path / "better" / "report.json").read_text())
  assert report["held_out"] is True and report["improved_in"] == "world model"
  first, last = report["rounds"]
  assert first["true_gain"] == 0.0 and last["kept_episodes"] == 2 and last["decisions"] == 16
  for key in ("true_value", "true_gain_stderr", "imagined_value", "gap"):
    assert np.isfinite(last[key])
  assert len(last["true_returns"]) == 4
  assert load_policy(better).params is not None
  capsys.readouterr()
  assert cli.main(["improve", "--workdir", str(trained_workdir), "--policy", start, "--out",
                   better]) == 2
  assert "exists" in capsys.readouterr().err


@pytest.mark.integration
def test_true_environment_improvement_runs_without_the_world_model_in_groups(trained_workdir):
  from wmjax import registry
  from wmjax.model import load_model
  from wmjax.train.improve import improve_on_task
  model = load_model(str(trained_workdir))
  task = registry.control_task("reach", model.config)
  policy = LearnedPolicy.create(model.action_stats, model.config.data.normalization,
                                context=model.config.rollout.context, chunk=1,
                                frame_shape=model.image_shape, key=jax.random.key(0),
                                controls=task.controls, channels=(8, 8), hidden=16)
  settings = ImproveSettings(rounds=1, rollouts=8, group=4, keep=0.25, fit_steps=2)
  _, report = improve_on_task(model, policy, task, settings, evaluation_states=4,
                              in_true_environment=True, imagine=False)
  last = report["rounds"][-1]
  assert last["kept_episodes"] == 2  # one of each start state's four
  assert "imagined_value" not in last and np.isfinite(last["true_gain"])
