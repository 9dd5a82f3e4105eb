"""The state a Push-T frame shows, read off its pixels in JAX (jit- and scan-safe).

:func:`perceived_state` reads the agent's and the T's place and the T's turn from a frame, as
:mod:`.metrics` reads them to score frames, so that a world model can be told the poses its
context frames show: the same reading applies to the simulator's renders (training data) and to
frames the model drew itself (closed-loop rollouts).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from wmjax.tasks.pusht.simulator import object_masks, world_centroid

STATE_FEATURES = 6  # agent x, y; T x, y (world units); cos, sin of the T's angle


def block_angle(mask: jax.Array) -> jax.Array:
  """The T's angle (radians, the simulator's ``block_angle``) from its pixels ``mask [..., H,
  W]``, as :func:`.metrics.block_pose` finds it: the stem lies along the mask's axis of largest
  spread, towards the side its third moment along that axis is positive."""
  h, w = mask.shape[-2:]
  m = mask.astype(jnp.float32)
  n = jnp.maximum(m.sum((-2, -1)), 1.0)
  rows, cols = jnp.arange(h) + 0.5, jnp.arange(w) + 0.5
  cy = (m * rows[:, None]).sum((-2, -1)) / n
  cx = (m * cols).sum((-2, -1)) / n
  dy = rows[:, None] - cy[..., None, None]
  dx = cols - cx[..., None, None]
  sxx, syy, sxy = ((m * d).sum((-2, -1)) / n for d in (dx * dx, dy * dy, dx * dy))
  axis = 0.5 * jnp.arctan2(2 * sxy, sxx - syy)
  vx, vy = jnp.cos(axis), jnp.sin(axis)
  skew = (m * (dx * vx[..., None, None] + dy * vy[..., None, None]) ** 3).sum((-2, -1))
  sign = jnp.where(skew < 0, -1.0, 1.0)
  return jnp.arctan2(-sign * vx, sign * vy)


def perceived_state(frames: jax.Array) -> jax.Array:
  """``frames [..., H, W, 3]`` in [-1, 1] -> ``[..., 6]`` float32: the agent's ``(x, y)`` and
  the T's ``(x, y)`` (world units, the frame's centre where an object is not seen) and the cos
  and sin of the T's angle (1, 0 where it is not seen)."""
  block, agent = object_masks(frames)
  block_xy, block_seen = world_centroid(block)
  agent_xy, _ = world_centroid(agent)
  angle = jnp.where(block_seen, block_angle(block), 0.0)
  return jnp.concatenate([agent_xy, block_xy, jnp.cos(angle)[..., None],
                          jnp.sin(angle)[..., None]], -1).astype(jnp.float32)

