"""Gridworld metrics: where each coloured square is in a frame and how well its shape is drawn.

* :func:`color_masks` / :func:`color_centroids`: each colour's pixels and their centroid;
* :func:`square_position_error`: detected vs true square centres (pixels);
* :func:`square_iou`: IoU of each square's predicted and true pixels, and whether the predicted
  square is in one piece;
* :data:`FRAME_METRICS`: the per-frame metrics ``wmjax evaluate`` and training's evaluation add for
  the gridworld (``square_error_px``, ``square_iou``, ``square_one_component``, and the masked
  MSE over the squares' pixels).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from wmjax.frames import to_uint8
from wmjax.tasks.gridworld.dataset import COLORS
from wmjax.registry import FrameMetrics


def color_masks(frames, colors: np.ndarray, tolerance: float = 60.0) -> np.ndarray:
  """Pixels within ``tolerance`` (per channel, 0-255) of each colour: ``frames [..., H, W, 3]``,
  ``colors [n, 3]`` -> ``[..., H, W, n]`` bool."""
  pixels = to_uint8(frames).astype(np.float64)
  return np.abs(pixels[..., None, :] - np.asarray(colors, np.float64)).max(-1) < tolerance


def color_centroids(frames, colors: np.ndarray, tolerance: float = 60.0
                    ) -> tuple[np.ndarray, np.ndarray]:
  """Centroid (y, x) of the pixels of each colour: ``frames [..., H, W, 3]``, ``colors [n, 3]``
  -> centroids ``[..., n, 2]`` and found ``[..., n]`` (False where no pixel is that colour)."""
  mask = color_masks(frames, colors, tolerance)  # [..., H, W, n]
  h, w = mask.shape[-3:-1]
  ys, xs = np.mgrid[0:h, 0:w]
  count = mask.sum((-3, -2))
  with np.errstate(invalid="ignore", divide="ignore"):
    cy = (mask * ys[..., None]).sum((-3, -2)) / count
    cx = (mask * xs[..., None]).sum((-3, -2)) / count
  # pixel (i, j) covers [i, i+1): its centre is at i + 0.5
  return np.stack([cy + 0.5, cx + 0.5], -1), count > 0


def square_position_error(frames, true_centres: np.ndarray, colors: np.ndarray,
                          missing_penalty: float) -> tuple[np.ndarray, np.ndarray]:
  """Distance (pixels) between each square's detected and true centre ``[..., n]``, a square
  not found in a frame counting ``missing_penalty``; also returns the found mask."""
  centres, found = color_centroids(frames, colors)
  error = np.linalg.norm(centres - true_centres, axis=-1)
  return np.where(found, error, missing_penalty), found


def square_iou(pred, truth, colors: np.ndarray, tolerance: float = 60.0
               ) -> tuple[np.ndarray, np.ndarray]:
  """Shape agreement of coloured squares: ``pred`` and ``truth`` ``[..., H, W, 3]``, ``colors
  [n, 3]`` -> (IoU of each colour's predicted and true pixel masks ``[..., n]``, whether the
  predicted mask is one 4-connected component ``[..., n]``).

  A colour absent from both frames (a square hidden under a later one) has IoU 1; absent from
  one of them, 0. A centroid can sit on the true position while the pixels scatter around it;
  the IoU cannot.
  """
  pred_mask = color_masks(pred, colors, tolerance)  # [..., H, W, n]
  true_mask = color_masks(truth, colors, tolerance)
  if pred_mask.shape != true_mask.shape:
    raise ValueError(f"pred and truth must have the same shape, got {np.shape(pred)} and "
                     f"{np.shape(truth)}")
  intersection = (pred_mask & true_mask).sum((-3, -2))
  union = (pred_mask | true_mask).sum((-3, -2))
  with np.errstate(invalid="ignore", divide="ignore"):
    iou = np.where(union > 0, intersection / np.maximum(union, 1), 1.0)
  h, w, n = pred_mask.shape[-3:]
  masks = np.moveaxis(pred_mask, -1, -3).reshape(-1, h, w)  # [..., n, H, W] flattened
  components = np.array([scipy.ndimage.label(m)[1] for m in masks]).reshape(pred_mask.shape[:-3]
                                                                              + (n,))
  return iou, components == 1


def _colors(extras) -> np.ndarray:
  return COLORS[:np.shape(extras["square_positions"])[-2]]


def square_metrics(pred, truth, extras) -> dict[str, np.ndarray]:
  """``square_error_px``, ``square_iou`` and ``square_one_component`` per frame ``[E, T]`` of
  ``pred`` against ``truth`` (``[E, T, S, S, 3]``) given the true ``square_positions``
  ``[E, T, n, 2]`` in ``extras``; nothing without them."""
  if "square_positions" not in extras:
    return {}
  colors = _colors(extras)
  error, _ = square_position_error(pred, extras["square_positions"], colors,
                                   missing_penalty=np.shape(truth)[-3] / 2)
  iou, one_component = square_iou(pred, truth, colors)
  return {"square_error_px": error.mean(-1), "square_iou": iou.mean(-1),
          "square_one_component": one_component.mean(-1)}


def square_masks(pred, truth, extras) -> np.ndarray | None:
  """Object masks ``[E, T, S, S]``: the squares' pixels in the truth or the prediction."""
  if "square_positions" not in extras:
    return None
  colors = _colors(extras)
  return (color_masks(truth, colors) | color_masks(pred, colors)).any(-1)


FRAME_METRICS = FrameMetrics(
    compute=square_metrics, object_masks=square_masks, headline="square_error_px",
    lower_is_better={"square_error_px": True, "square_iou": False,
                     "square_one_component": False})
