"""The true gridworld, steppable: a pure-JAX batched environment and a gymnasium wrapper.

The state is the square centres ``[B, n, 2]`` ((y, x) pixels), as the dataset stores them in
``observation/square_positions``. :func:`step` moves every square by its velocity in the action
``[B, 2n]`` exactly as :func:`wmjax.tasks.gridworld.dataset.simulate` does (snapped to the pixel
grid and clipped to the frame), after clipping the velocity to ``[-max_speed, max_speed]``, the
range the data covers; :func:`render` draws frames exactly as
:func:`wmjax.tasks.gridworld.dataset.render` does (later squares on top). Both are traceable,
so :func:`run_policy` rolls a pure-JAX policy out for a whole batch inside one ``lax.scan``, the
way :func:`wmjax.eval.policy_eval.scan_episodes` rolls it out in a world model.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from wmjax.frames import to_model
from wmjax.policy import join_policy, split_policy
from wmjax.tasks.gridworld.dataset import COLORS, GridworldConfig


def step(config: GridworldConfig, centres: jax.Array, actions: jax.Array) -> jax.Array:
  """Square centres ``[..., n, 2]`` after the velocities ``actions [..., 2n]`` (pixels/step)."""
  n, half = config.num_squares, config.square_size / 2
  velocity = jnp.clip(actions, -config.max_speed, config.max_speed)
  moved = centres + velocity.reshape(velocity.shape[:-1] + (n, 2))
  if config.snap_to_pixels:
    moved = jnp.round(moved - half) + half
  return jnp.clip(moved, half, config.image_size - half).astype(jnp.float32)


def render(config: GridworldConfig, centres: jax.Array) -> jax.Array:
  """Square centres ``[..., n, 2]`` -> uint8 frames ``[..., S, S, 3]``."""
  size, pixels = config.square_size, jnp.arange(config.image_size)
  corner = jnp.round(centres - size / 2).astype(jnp.int32)  # [..., n, 2] top-left pixel
  inside = (pixels >= corner[..., None]) & (pixels < corner[..., None] + size)  # [..., n, 2, S]
  masks = inside[..., 0, :, None] & inside[..., 1, None, :]  # [..., n, S, S]
  frame = jnp.zeros(centres.shape[:-2] + (config.image_size, config.image_size, 3), jnp.uint8)
  for i in range(config.num_squares):
    frame = jnp.where(masks[..., i, :, :, None], jnp.asarray(COLORS[i]), frame)
  return frame


def run_policy(config: GridworldConfig, policy: Any, centres, steps: int, key: jax.Array
               ) -> dict[str, jax.Array]:
  """Roll ``policy(frames [B, 1, S, S, 3] in [-1, 1], key) -> actions [B, k, 2n]`` out for
  ``steps`` steps from ``centres [B, n, 2]``, calling it on the newest frame whenever its
  previous chunk is used up (call ``i`` with ``fold_in(key, i)``, as
  :func:`wmjax.eval.policy_eval.scan_episodes` calls it in a world model). Returns ``frames
  [B, 1+steps, S, S, 3]`` in [-1, 1], the actions ``[B, steps, 2n]`` and the centres
  ``[B, 1+steps, n, 2]``. A policy that is a pytree of arrays (a
  :class:`wmjax.policy.LearnedPolicy`) is traced: new parameters reuse the compiled scan."""
  centres = jnp.asarray(centres, jnp.float32)
  if centres.ndim != 3 or centres.shape[1:] != (config.num_squares, 2):
    raise ValueError(f"centres must be [B, {config.num_squares}, 2], got {centres.shape}")
  if steps < 1:
    raise ValueError(f"steps must be >= 1, got {steps}")
  static, leaves = split_policy(policy)
  return _run_fn(config, static, steps)(leaves, centres, key)


@functools.lru_cache(maxsize=16)
def _run_fn(config: GridworldConfig, static_policy, steps: int):
  """The jitted scan for one (config, policy structure, steps)."""

  @jax.jit
  def run(leaves, centres, key):
    policy = join_policy(static_policy, leaves)
    frame = to_model(render(config, centres), xp=jnp)[:, None]
    chunk = jax.eval_shape(policy, frame, key).shape[1]

    def call(state, i):
      actions = policy(to_model(render(config, state), xp=jnp)[:, None], jax.random.fold_in(key, i))
      path = []
      for j in range(chunk):
        state = step(config, state, actions[:, j])
        path.append(state)
      return state, (jnp.stack(path, 1), actions)

    _, (path, actions) = jax.lax.scan(call, centres, jnp.arange(-(-steps // chunk)))
    path = jnp.moveaxis(path, 0, 1).reshape((centres.shape[0], -1) + centres.shape[1:])[:, :steps]
    actions = jnp.moveaxis(actions, 0, 1).reshape((centres.shape[0], -1, actions.shape[-1]))
    path = jnp.concatenate([centres[:, None], path], 1)
    return {"frames": to_model(render(config, path), xp=jnp),
            "actions": actions[:, :steps].astype(jnp.float32), "centres": path}

  return run
