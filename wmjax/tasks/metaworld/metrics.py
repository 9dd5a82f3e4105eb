"""Per-view frame metrics of a multi-camera MetaWorld model, registered for ``wmjax evaluate``.

A frame holds the views side by side (``[H, V * H, 3]``, square views); each metric is taken per
view: ``view{v}_mse`` (pixels in [-1, 1]) and ``view{v}_psnr`` (dB, peak 2). A model can look
right in the third-person view and lose the wrist view, which a whole-frame number averages away.
The arm's own metrics (the end effector's pixel error, the object's state) need a reader fitted
to the data's frames: :mod:`.reader`.
"""

from __future__ import annotations

import numpy as np

from wmjax.frames import to_model
from wmjax.registry import FrameMetrics


def split_views(frames) -> np.ndarray:
  """``[..., H, V*H, C]`` (square views side by side) -> ``[..., V, H, H, C]``."""
  frames = np.asarray(frames)
  h, w = frames.shape[-3:-1]
  if w % h:
    raise ValueError(f"frames of square views side by side must be a whole number of views "
                     f"wide, got {h}x{w}")
  views = frames.reshape(frames.shape[:-2] + (w // h, h, frames.shape[-1]))
  return np.moveaxis(views, -3, -4)


def view_metrics(pred, truth, extras) -> dict[str, np.ndarray]:
  """``pred``, ``truth [E, T, H, V*H, 3]`` -> ``{view{v}_mse, view{v}_psnr: [E, T]}``."""
  del extras
  p, t = split_views(to_model(np.asarray(pred))), split_views(to_model(np.asarray(truth)))
  mse = np.mean((np.asarray(p, np.float64) - np.asarray(t, np.float64)) ** 2, axis=(-3, -2, -1))
  out = {}
  for v in range(mse.shape[-1]):
    out[f"view{v}_mse"] = mse[..., v]
    out[f"view{v}_psnr"] = 10 * np.log10(4.0 / np.maximum(mse[..., v], 1e-10))
  return out


FRAME_METRICS = FrameMetrics(
    compute=view_metrics, headline="view0_mse",
    lower_is_better={f"view{v}_{m}": m == "mse" for v in range(4) for m in ("mse", "psnr")})
