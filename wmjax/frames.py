"""Frame value ranges: RGB frames are uint8 on disk and float32 in [-1, 1] in the model.

* :func:`to_model` — uint8 -> float32 in [-1, 1] (floats are taken to be in range already);
* :func:`to_unit` — either -> float32 in [0, 1], what pixel metrics see;
* :func:`to_uint8` — either -> uint8, rounded, on the host.

Shapes are kept (``[..., H, W, C]``, any leading axes).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def to_model(frames) -> np.ndarray:
  """uint8 frames -> float32 in [-1, 1] on the host; float frames are taken to be in [-1, 1]
  already and only cast to float32."""
  frames = np.asarray(frames)
  if frames.dtype == np.uint8:
    return frames.astype(np.float32) / 127.5 - 1.0
  return frames.astype(np.float32, copy=False)


def to_unit(frames) -> jax.Array:
  """uint8 or [-1, 1] floats -> float32 in [0, 1] (floats clipped)."""
  frames = jnp.asarray(frames)
  if frames.dtype == jnp.uint8:
    return frames.astype(jnp.float32) / 255.0
  return jnp.clip((frames.astype(jnp.float32) + 1.0) / 2.0, 0.0, 1.0)


def to_uint8(frames) -> np.ndarray:
  """uint8 or [-1, 1] floats -> uint8 (rounded, clipped), on the host."""
  frames = np.asarray(frames)
  if frames.dtype == np.uint8:
    return frames
  return np.round(np.clip((frames.astype(np.float32) + 1.0) * 127.5, 0.0, 255.0)).astype(np.uint8)
