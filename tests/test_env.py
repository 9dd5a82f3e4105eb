"""WorldModelEnv: normalisation of raw actions, growing context, chunks shorter than the horizon,
recording, rewards, truncation and input errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import tiny_world_model
from wmjax.data.stats import ActionStats
from wmjax.env import WorldModelEnv
from wmjax.rollout import rollout

pytestmark = pytest.mark.unit


def _stats(dim):
  rng = np.random.default_rng(0)
  return ActionStats.compute(rng.normal(3.0, 2.0, (500, dim)), "toy", gripper_dim=None)


def _setup(b=2, c=2):
  wm, params = tiny_world_model("wpe_600m.py", "sampling.num_steps=2", frame_shape=(8, 8, 16))
  key = jax.random.key(1)
  context = jax.random.normal(key, (b, c, 8, 8, 16))
  raw = np.asarray(jax.random.normal(jax.random.key(2), (b, 7, 7))) * 2.0 + 3.0
  return wm, params, context, raw


@pytest.mark.slow
def test_raw_actions_are_normalised_with_the_checkpoint_statistics():
  wm, params, context, raw = _setup()
  stats = _stats(7)
  env = WorldModelEnv(wm, params, context=2, horizon=3, action_stats=stats, seed=4)
  first, info = env.reset(context)
  assert first.shape == (2, 2, 8, 8, 16) and info["frames"] == 2
  for lo in range(0, 7, 3):
    new, reward, terminated, truncated, info = env.step(raw[:, lo:lo + 3])
    assert new.shape == (2, min(3, 7 - lo), 8, 8, 16)
    assert reward.shape == (2,) and not terminated.any() and not truncated.any()
  assert info == {"frames": 9, "step": 3}
  expected = rollout(wm, params, context, stats.normalize(raw), jax.random.key(4), horizon=3)
  np.testing.assert_allclose(env.video(), expected, rtol=1e-5, atol=1e-5)
  # with the raw actions unnormalised the frames differ: normalisation was applied
  unnormalised = rollout(wm, params, context, raw, jax.random.key(4), horizon=3)
  assert float(jnp.abs(unnormalised - expected).max()) > 1e-3


@pytest.mark.slow
def test_context_grows_to_its_length_and_keeps_known_actions():
  """Started from one frame, the window grows to c frames; the actions between them are known."""
  wm, params, context, raw = _setup(b=1, c=1)
  env = WorldModelEnv(wm, params, context=3, horizon=2, seed=0)
  env.reset(context)
  env.step(raw[:, :2])
  assert env._window.shape[1] == 3 and env._history.shape[1] == 2 and env._known.all()
  env.step(raw[:, 2:3])  # a chunk shorter than the horizon
  assert env._window.shape[1] == 3
  np.testing.assert_array_equal(env._history, raw[:, 1:3])
  assert env.video().shape == (1, 4, 8, 8, 16)


@pytest.mark.slow
def test_rewards_truncation_and_uint8_frames():
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2", "model.in_channels=3",
                                frame_shape=(8, 8, 3))
  frames = np.random.default_rng(0).integers(0, 256, (3, 1, 8, 8, 3), dtype=np.uint8)
  env = WorldModelEnv(wm, params, context=1, horizon=3, max_steps=6, frame_shape=(8, 8, 3),
                      reward_fn=lambda new, instruction: new.mean((1, 2, 3, 4)) + len(instruction))
  start, _ = env.reset(frames, instruction="push the block")
  np.testing.assert_allclose(start, frames / 127.5 - 1.0, atol=1e-6)
  new, reward, _, truncated, _ = env.step(np.zeros((3, 3, 7)))
  np.testing.assert_allclose(reward, np.asarray(new).mean((1, 2, 3, 4)) + 14, rtol=1e-5)
  assert not truncated.any()
  _, _, _, truncated, info = env.step(np.zeros((3, 2, 7)))
  assert truncated.all() and info["frames"] == 6


@pytest.mark.parametrize("call,message", [
    (lambda env: env.step(np.zeros((2, 3, 7))), r"call reset"),
    (lambda env: env.reset(np.zeros((2, 3, 8, 8, 16))), r"1 <= c0 <= 2, got shape \(2, 3, 8"),
    (lambda env: env.reset(np.zeros((2, 1, 6, 8, 16))), r"frames must be \(8, 8, 16\)"),
    (lambda env: (env.reset(np.zeros((2, 1, 8, 8, 16))), env.step(np.zeros((2, 4, 7)))),
     r"action_chunk must be \[B=2, k, A=7\] with 1 <= k <= 3, got shape \(2, 4, 7\)"),
    (lambda env: (env.reset(np.zeros((2, 1, 8, 8, 16))), env.step(np.zeros((3, 2, 7)))),
     r"action_chunk must be \[B=2"),
    (lambda env: (env.reset(np.zeros((2, 1, 8, 8, 16))), env.step(np.full((2, 2, 7), np.nan))),
     r"action_chunk contain NaN"),
    (lambda env: env.reset(np.zeros((2, 2, 8, 8, 16)), context_actions=np.zeros((2, 2, 7))),
     r"context_actions must be \[B=2, k, A=7\] with 1 <= k <= 1"),
])
def test_bad_environment_input_raises_clear_error(call, message):
  wm, params = tiny_world_model("wpe_600m.py", "sampling.num_steps=2", frame_shape=(8, 8, 16))
  env = WorldModelEnv(wm, params, context=2, horizon=3, frame_shape=(8, 8, 16))
  with pytest.raises((ValueError, RuntimeError), match=message):
    call(env)


def test_window_must_fit_the_model():
  wm, params = tiny_world_model("wpe_600m.py", frame_shape=(8, 8, 16))
  with pytest.raises(ValueError, match=r"context \+ horizon <= 8"):
    WorldModelEnv(wm, params, context=4, horizon=5)


def test_keyboard_driver_maps_keys_to_action_chunks():
  from wmjax.interactive import KeyboardDriver
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2", "model.in_channels=3",
                                "model.action_dim=3", frame_shape=(8, 8, 3))
  env = WorldModelEnv(wm, params, context=1, horizon=3, seed=0)
  driver = KeyboardDriver(env, speed=2.0, axes=(1, 0), rest=[0.0, 0.0, 1.0])
  np.testing.assert_array_equal(driver.action("ArrowUp"), [0.0, -2.0, 1.0])  # (x, y) slots
  np.testing.assert_array_equal(driver.action("ArrowRight"), [2.0, 0.0, 1.0])
  driver.reset(np.zeros((1, 1, 8, 8, 3), np.uint8))
  new = driver.press("ArrowLeft")
  assert new.shape == (3, 8, 8, 3) and driver.video().shape == (4, 8, 8, 3)
  # the frames are the world model's for those actions
  replay = WorldModelEnv(wm, params, context=1, horizon=3, seed=0)
  replay.reset(np.zeros((1, 1, 8, 8, 3), np.uint8))
  expected, *_ = replay.step(np.repeat(driver.action("ArrowLeft")[None, None], 3, axis=1))
  np.testing.assert_allclose(new, expected[0], atol=1e-6)
  with pytest.raises(ValueError, match="key must be one of"):
    driver.press("Space")
  with pytest.raises(ValueError, match="axes must be two different"):
    KeyboardDriver(env, axes=(0, 0))


@pytest.mark.parametrize("batch", [8, 3])  # split over the 8 devices, or not divisible
def test_steps_compile_one_program(batch):
  """The window reset makes and the one a step leaves are laid out alike: one compile, not a
  second at the second step (a loaded model's parameters live on the rollout mesh)."""
  from jax.sharding import NamedSharding, PartitionSpec

  from wmjax import rollout
  from wmjax.parallel import local_data_mesh
  wm, params = tiny_world_model("wpe_600m.py", "sampling.num_steps=2", frame_shape=(8, 8, 16))
  params = jax.device_put(params, NamedSharding(local_data_mesh(), PartitionSpec()))
  env = WorldModelEnv(wm, params, context=1, horizon=1, action_stats=_stats(7), seed=0)
  env.reset(np.zeros((batch, 1, 8, 8, 16), np.float32))
  before = rollout._sample_block_jit._cache_size()
  for _ in range(3):
    env.step(np.zeros((batch, 1, 7), np.float32))
  assert rollout._sample_block_jit._cache_size() - before == 1


def test_parameters_on_the_host_step_too():
  wm, params = tiny_world_model("wpe_600m.py", "sampling.num_steps=2", frame_shape=(8, 8, 16))
  env = WorldModelEnv(wm, jax.tree.map(np.asarray, params), context=1, horizon=1,
                      action_stats=_stats(7), seed=0)
  env.reset(np.zeros((2, 1, 8, 8, 16), np.float32))
  new, *_ = env.step(np.zeros((2, 1, 7), np.float32))
  assert new.shape == (2, 1, 8, 8, 16) and np.isfinite(np.asarray(new)).all()
