"""Blockwise autoregressive rollout: scan == closed-loop environment, padding, guidance and input
checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import jit_apply, tiny_world_model
from wmjax.env import WorldModelEnv
from wmjax.rollout import rollout, sample_block

pytestmark = pytest.mark.unit

CASES = [  # (config, overrides, c, h, N)
    ("irasim.py:S", (), 1, 3, 7),
    ("irasim.py:S", ("sampling.matrix='pyramid'",), 2, 3, 8),
    ("wpe_600m.py", ("sampling.num_steps=3",), 3, 2, 5),
    ("wpe_600m.py", ("sampling.matrix='autoregressive'", "sampling.num_steps=2"), 2, 4, 4),
]


def _inputs(wm, b, c, n, seed=0, channels=4):
  k1, k2 = jax.random.split(jax.random.key(seed))
  context = jax.random.normal(k1, (b, c, 8, 8, channels))
  actions = jax.random.normal(k2, (b, n, wm.network.action_dim))
  return context, actions


def _closed_loop(wm, params, context, actions, rng, horizon):
  """The rollout driven chunk by chunk through WorldModelEnv (the closed-loop face)."""
  env = WorldModelEnv(wm, params, context=context.shape[1], horizon=horizon, seed=rng)
  env.reset(context)
  for lo in range(0, actions.shape[1], horizon):
    env.step(actions[:, lo:lo + horizon])
  return env.video()


@pytest.mark.parametrize("config,overrides,c,h,n", CASES)
@pytest.mark.slow
def test_open_loop_scan_equals_closed_loop_environment(config, overrides, c, h, n):
  """WorldModelEnv stepped chunk by chunk == the jitted scan, same key and actions (N % h != 0
  included: the last chunk is shorter)."""
  channels = 16 if config.startswith("wpe") else 4
  wm, params = tiny_world_model(config, *overrides, frame_shape=(8, 8, channels))
  context, actions = _inputs(wm, 2, c, n, channels=channels)
  rng = jax.random.key(7)
  out = rollout(wm, params, context, actions, rng, horizon=h)
  assert out.shape == (2, c + n, 8, 8, channels)
  np.testing.assert_array_equal(out[:, :c], context)
  expected = _closed_loop(wm, params, context, actions, rng, h)
  assert expected.shape == out.shape
  np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)
  assert float(jnp.abs(out[:, c:]).mean()) > 0  # frames were generated


@pytest.mark.slow
def test_rollout_sharded_over_the_batch_equals_unsharded():
  assert jax.device_count() == 8
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2")
  context, actions = _inputs(wm, 8, 1, 5)
  mesh = jax.make_mesh((8,), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
  batch = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
  rng = jax.random.key(0)
  sharded = rollout(wm, params, jax.device_put(context, batch), jax.device_put(actions, batch), rng,
                    horizon=3)
  assert len(sharded.sharding.device_set) == 8
  assert sharded.sharding.shard_shape(sharded.shape)[0] == 1
  np.testing.assert_allclose(sharded, rollout(wm, params, context, actions, rng, horizon=3),
                             rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_context_actions_condition_the_first_block():
  wm, params = tiny_world_model("wpe_600m.py", "sampling.num_steps=2", frame_shape=(8, 8, 16))
  context, actions = _inputs(wm, 1, 3, 4, channels=16)
  rng = jax.random.key(0)
  without = rollout(wm, params, context, actions, rng, horizon=2)
  known = rollout(wm, params, context, actions, rng, horizon=2,
                  context_actions=jnp.ones((1, 2, 7)))
  assert float(jnp.abs(without - known)[:, 3:].max()) > 1e-4


def test_padding_does_not_change_earlier_frames_of_a_causal_model():
  """N not divisible by h: the padded block matches a longer rollout on the frames both produce."""
  wm, params = tiny_world_model("wpe_600m.py", "sampling.num_steps=2", frame_shape=(8, 8, 16))
  context, actions = _inputs(wm, 2, 2, 6, channels=16)
  rng = jax.random.key(3)
  short = rollout(wm, params, context, actions[:, :5], rng, horizon=3)
  full = rollout(wm, params, context, actions, rng, horizon=3)
  assert short.shape[1] == 7
  np.testing.assert_allclose(short, full[:, :7], rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_guidance_combines_conditional_and_null_outputs():
  wm, params = tiny_world_model("irasim.py:S", "sampling.guidance_scale=3.0")
  x = jax.random.normal(jax.random.key(0), (2, 4, 8, 8, 4))
  levels = jnp.full((2, 4), 500)
  actions = jax.random.normal(jax.random.key(1), (2, 3, 7))
  mask = jnp.ones((2, 3), bool)
  got = jax.jit(wm.denoise)(params, x, levels, actions, mask)
  t = wm.process.model_time(levels)
  apply = jit_apply(wm.network)
  cond = apply(params, x, t, actions, mask)
  null = apply(params, x, t, actions, mask, jnp.ones((2,), bool))
  np.testing.assert_allclose(got, null + 3.0 * (cond - null), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("case,message", [
    ("action_dim", r"actions must have dimension A=7, got 6"),
    ("patch", r"divisible by the patch size 2, got 9x8"),
    ("too_many_frames", r"context \+ horizon = 2 \+ 7 frames exceeds the 8 frames"),
    ("nan_actions", r"actions contain NaN or inf"),
    ("nan_context", r"context frames contain NaN or inf"),
    ("batch", r"batch sizes differ: context frames have B=2, actions have B=3"),
    ("channels", r"must have 4 channels, got 3"),
    ("context_rank", r"context frames must be \[B, c, H, W, C\], got shape \(2, 8, 8, 4\)"),
    ("horizon", r"horizon must be a positive integer, got 0"),
    ("context_actions", r"context_actions must be \[B, c-1, A\] = \(2, 1, 7\), got \(2, 2, 7\)"),
])
def test_bad_rollout_input_raises_clear_error(case, message):
  wm, params = tiny_world_model("irasim.py:S")
  context = jnp.zeros((2, 2, 8, 8, 4))
  actions = jnp.zeros((2, 5, 7))
  kwargs = dict(horizon=3)
  if case == "action_dim":
    actions = jnp.zeros((2, 5, 6))
  elif case == "patch":
    context = jnp.zeros((2, 2, 9, 8, 4))
  elif case == "too_many_frames":
    kwargs["horizon"] = 7
  elif case == "nan_actions":
    actions = actions.at[1, 2, 0].set(jnp.nan)
  elif case == "nan_context":
    context = context.at[0, 0, 0, 0, 0].set(jnp.inf)
  elif case == "batch":
    actions = jnp.zeros((3, 5, 7))
  elif case == "channels":
    context = jnp.zeros((2, 2, 8, 8, 3))
  elif case == "context_rank":
    context = jnp.zeros((2, 8, 8, 4))
  elif case == "horizon":
    kwargs["horizon"] = 0
  elif case == "context_actions":
    kwargs["context_actions"] = jnp.zeros((2, 2, 7))
  with pytest.raises(ValueError, match=message):
    rollout(wm, params, context, actions, jax.random.key(0), **kwargs)


def test_sample_block_checks_its_window():
  wm, params = tiny_world_model("irasim.py:S")
  context = jnp.zeros((2, 2, 8, 8, 4))
  with pytest.raises(ValueError, match=r"window_mask must be \[B, c\+h-1\]"):
    sample_block(wm, params, context, jnp.zeros((2, 4, 7)), jax.random.key(0),
                 jnp.ones((2, 3), bool))
  out = sample_block(wm, params, context, jnp.zeros((2, 4, 7)), jax.random.key(0))
  assert out.shape == (2, 3, 8, 8, 4)


def test_action_mask_makes_padded_trajectories_match_their_own_rollout():
  """A trajectory padded with masked actions gets the frames of its own shorter rollout, even in
  a model whose frames attend to the whole window (frame mode)."""
  wm, params = tiny_world_model("irasim.py:S", "sampling.num_steps=2")
  context, actions = _inputs(wm, 2, 1, 6)
  rng = jax.random.key(5)
  alone = rollout(wm, params, context, actions[:, :5], rng, horizon=3)
  mask = jnp.arange(6)[None].repeat(2, 0) < 5
  padded = rollout(wm, params, context, actions.at[:, 5].set(9.0), rng, horizon=3,
                   action_mask=mask)
  np.testing.assert_allclose(padded[:, :6], alone, rtol=1e-5, atol=1e-5)
  with pytest.raises(ValueError, match=r"action_mask must be \[B, N\]"):
    rollout(wm, params, context, actions, rng, horizon=3, action_mask=mask[:, :4])


@pytest.mark.parametrize("config,overrides,c,h", [
    ("wpe_600m.py", ("sampling.num_steps=3",), 3, 2),
    ("wpe_600m.py", ("sampling.matrix='pyramid'", "sampling.num_steps=2",
                     "sampling.guidance_scale=2.0", "model.temporal_pos='rope'"), 2, 3),
    ("irasim.py:S", ("model.causal_temporal=True", "model.cond='video'", "sampling.num_steps=3",
                     "model.views=2"), 1, 4),  # two views side by side
])
@pytest.mark.slow
def test_kv_cache_rollout_equals_the_uncached_rollout(config, overrides, c, h):
  """sampling.kv_cache encodes the context once per block; the frames are those of the rollout
  that runs the whole window at every step, open loop and closed loop (float32 rounding of
  other matmul shapes, compounded over blocks, is the only difference)."""
  channels = 16 if config.startswith("wpe") else 4
  wm, params = tiny_world_model(config, *overrides, frame_shape=(8, 8, channels))
  cached, _ = tiny_world_model(config, *overrides, "sampling.kv_cache=True",
                               frame_shape=(8, 8, channels))
  context, actions = _inputs(wm, 2, c, 7, channels=channels)
  rng = jax.random.key(5)
  want = rollout(wm, params, context, actions, rng, horizon=h)
  np.testing.assert_allclose(rollout(cached, params, context, actions, rng, horizon=h), want,
                             rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(_closed_loop(cached, params, context, actions, rng, h), want,
                             rtol=1e-4, atol=1e-4)
