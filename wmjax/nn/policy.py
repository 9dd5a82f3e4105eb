"""A small learnable visuomotor policy: the newest ``c`` frames -> a Gaussian over the next ``k``
normalised actions.

The frames are stacked along the channels with two coordinate channels (y and x in [-1, 1], so
that a convolution knows where a pixel is), read by strided 3x3 convolutions and an MLP; the
output is the mean of each of the ``k x A`` normalised actions and one learned log standard
deviation per action dimension (shared by the chunk's steps, independent of the frames).
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def coordinate_channels(height: int, width: int) -> jax.Array:
  """``[H, W, 2]``: each pixel's (y, x) centre scaled to [-1, 1]."""
  ys = (jnp.arange(height) + 0.5) / height * 2 - 1
  xs = (jnp.arange(width) + 0.5) / width * 2 - 1
  return jnp.stack(jnp.meshgrid(ys, xs, indexing="ij"), -1)


class FramePolicy(nn.Module):
  """``frames [B, c, H, W, 3]`` in [-1, 1] -> (mean ``[B, k, A]``, log_std ``[A]``) of the
  normalised actions. ``channels``: one stride-2 3x3 convolution per entry (the first has
  stride 1); ``hidden``: the MLP's width."""

  action_dim: int
  chunk: int = 1
  channels: Sequence[int] = (32, 64, 64)
  hidden: int = 256
  init_log_std: float = 0.0

  @nn.compact
  def __call__(self, frames: jax.Array) -> tuple[jax.Array, jax.Array]:
    if frames.ndim != 5 or frames.shape[-1] != 3:
      raise ValueError(f"frames must be [B, c, H, W, 3], got {frames.shape}")
    b, c, h, w, _ = frames.shape
    x = jnp.moveaxis(frames, 1, 3).reshape(b, h, w, 3 * c)  # the frames stacked as channels
    x = jnp.concatenate([x, jnp.broadcast_to(coordinate_channels(h, w), (b, h, w, 2))], -1)
    for i, width in enumerate(self.channels):
      x = nn.relu(nn.Conv(width, (3, 3), strides=1 if i == 0 else 2)(x))
    x = nn.relu(nn.Dense(self.hidden)(x.reshape(b, -1)))
    x = nn.relu(nn.Dense(self.hidden)(x))
    mean = nn.Dense(self.chunk * self.action_dim, kernel_init=nn.initializers.zeros)(x)
    log_std = self.param("log_std", nn.initializers.constant(self.init_log_std),
                         (self.action_dim,))
    return mean.reshape(b, self.chunk, self.action_dim), log_std
