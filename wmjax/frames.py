"""Frame value ranges: RGB frames are uint8 on disk and float32 in [-1, 1] in the model.

* :func:`to_model` — uint8 -> float32 in [-1, 1] (floats are taken to be in range already), on
  the host or, with ``xp=jnp``, on the device (inside ``jit`` too);
* :func:`to_unit` — either -> float32 in [0, 1], what pixel metrics see;
* :func:`to_uint8` — either -> uint8, rounded, on the host.

Shapes are kept (``[..., H, W, C]``, any leading axes).
"""

from __future__ import annotations

from types import ModuleType

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike


def to_model(frames: ArrayLike, xp: ModuleType = np) -> np.ndarray | jax.Array:
  """uint8 frames -> float32 in [-1, 1]; float frames are taken to be in [-1, 1] already and only
  cast to float32. ``xp``: the array module, ``np`` (a host array) or ``jnp`` (a device array;
  traced values inside ``jit`` stay traced)."""
  frames = xp.asarray(frames)
  if frames.dtype == np.uint8:
    return frames.astype(np.float32) / 127.5 - 1.0
  return frames.astype(np.float32, copy=False)


def to_unit(frames: ArrayLike) -> jax.Array:
  """uint8 or [-1, 1] floats -> float32 in [0, 1] (floats clipped)."""
  frames = jnp.asarray(frames)
  if frames.dtype == jnp.uint8:
    return frames.astype(jnp.float32) / 255.0
  return jnp.clip((frames.astype(jnp.float32) + 1.0) / 2.0, 0.0, 1.0)


def to_uint8(frames: ArrayLike) -> np.ndarray:
  """uint8 or [-1, 1] floats -> uint8 (rounded, clipped), on the host."""
  frames = np.asarray(frames)
  if frames.dtype == np.uint8:
    return frames
  return np.round(np.clip((frames.astype(np.float32) + 1.0) * 127.5, 0.0, 255.0)).astype(np.uint8)
