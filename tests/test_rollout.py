"""Blockwise autoregressive rollout: scan == explicit loop, padding, guidance and input checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import tiny_world_model
from wmjax.rollout import rollout, sample_block

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


def _explicit_loop(wm, params, context, actions, rng, horizon):
  """The rollout written as a Python loop over blocks (the semantics the scan must reproduce)."""
  b, c = context.shape[:2]
  n, a = actions.shape[1:]
  num_blocks = -(-n // horizon)
  padded = jnp.concatenate([actions, jnp.zeros((b, num_blocks * horizon - n, a))], axis=1)
  known = jnp.concatenate([jnp.ones((b, n), bool), jnp.zeros((b, num_blocks * horizon - n), bool)], 1)
  history_actions = jnp.zeros((b, c - 1, a))
  history_known = jnp.zeros((b, c - 1), bool)
  frames = [context[:, i] for i in range(c)]
  keys = jax.random.split(rng, num_blocks)
  for k in range(num_blocks):
    block = slice(k * horizon, (k + 1) * horizon)
    window_actions = jnp.concatenate([history_actions, padded[:, block]], axis=1)
    window_mask = jnp.concatenate([history_known, known[:, block]], axis=1)
    ctx = jnp.stack(frames[-c:], axis=1)
    new = sample_block(wm, params, ctx, window_actions, keys[k], window_mask)
    frames += [new[:, i] for i in range(horizon)]
    history_actions = window_actions[:, -(c - 1):] if c > 1 else history_actions
    history_known = window_mask[:, -(c - 1):] if c > 1 else history_known
  return jnp.stack(frames, axis=1)[:, : c + n]


@pytest.mark.parametrize("config,overrides,c,h,n", CASES)
def test_scan_rollout_equals_python_loop(config, overrides, c, h, n):
  channels = 16 if config.startswith("wpe") else 4
  wm, params = tiny_world_model(config, *overrides, frame_shape=(8, 8, channels))
  context, actions = _inputs(wm, 2, c, n, channels=channels)
  rng = jax.random.key(7)
  out = rollout(wm, params, context, actions, rng, horizon=h)
  assert out.shape == (2, c + n, 8, 8, channels)
  np.testing.assert_array_equal(out[:, :c], context)
  expected = _explicit_loop(wm, params, context, actions, rng, h)
  np.testing.assert_allclose(out, expected, rtol=1e-4, atol=1e-4)
  assert float(jnp.abs(out[:, c:]).mean()) > 0  # frames were generated


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


def test_guidance_combines_conditional_and_null_outputs():
  wm, params = tiny_world_model("irasim.py:S", "sampling.guidance_scale=3.0")
  x = jax.random.normal(jax.random.key(0), (2, 4, 8, 8, 4))
  levels = jnp.full((2, 4), 500)
  actions = jax.random.normal(jax.random.key(1), (2, 3, 7))
  mask = jnp.ones((2, 3), bool)
  got = wm.denoise(params, x, levels, actions, mask)
  t = wm.process.model_time(levels)
  cond = wm.network.apply(params, x, t, actions, mask)
  null = wm.network.apply(params, x, t, actions, mask, jnp.ones((2,), bool))
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
