"""Video metrics on ``[..., T, H, W, C]`` frames in [-1, 1] (or uint8), context frames skipped by
the caller. PSNR is computed per frame on [0, 1] images; identical frames give +inf, which
:func:`psnr` caps at ``max_db`` so that means stay finite."""

from __future__ import annotations

import numpy as np


def to_unit(frames: np.ndarray) -> np.ndarray:
  """[-1, 1] floats or uint8 -> float64 in [0, 1]."""
  frames = np.asarray(frames)
  if frames.dtype == np.uint8:
    return frames.astype(np.float64) / 255.0
  return np.clip((frames.astype(np.float64) + 1.0) / 2.0, 0.0, 1.0)


def psnr(pred: np.ndarray, target: np.ndarray, max_db: float = 100.0) -> np.ndarray:
  """Per-frame PSNR in dB over the last three axes ``[H, W, C]``; identical frames -> ``max_db``."""
  mse = np.mean((to_unit(pred) - to_unit(target)) ** 2, axis=(-3, -2, -1))
  with np.errstate(divide="ignore"):
    db = 10.0 * np.log10(1.0 / mse)
  return np.minimum(db, max_db)


def color_centroids(frames: np.ndarray, colors: np.ndarray, tolerance: float = 60.0
                    ) -> tuple[np.ndarray, np.ndarray]:
  """Centroid (y, x) of the pixels of each colour: ``frames [..., H, W, 3]``, ``colors [n, 3]``
  -> centroids ``[..., n, 2]`` and found ``[..., n]`` (False where no pixel is that colour)."""
  pixels = np.round(to_unit(frames) * 255.0)
  h, w = pixels.shape[-3:-1]
  ys, xs = np.mgrid[0:h, 0:w]
  distance = np.abs(pixels[..., None, :] - np.asarray(colors, np.float64)).max(-1)  # [..., H, W, n]
  mask = distance < tolerance
  count = mask.sum((-3, -2))
  with np.errstate(invalid="ignore", divide="ignore"):
    cy = (mask * ys[..., None]).sum((-3, -2)) / count
    cx = (mask * xs[..., None]).sum((-3, -2)) / count
  # pixel (i, j) covers [i, i+1): its centre is at i + 0.5
  return np.stack([cy + 0.5, cx + 0.5], -1), count > 0


def square_position_error(frames: np.ndarray, true_centres: np.ndarray, colors: np.ndarray,
                          missing_penalty: float) -> tuple[np.ndarray, np.ndarray]:
  """Distance (pixels) between each square's detected and true centre ``[..., n]``, a square
  not found in a frame counting ``missing_penalty``; also returns the found mask."""
  centres, found = color_centroids(frames, colors)
  error = np.linalg.norm(centres - true_centres, axis=-1)
  return np.where(found, error, missing_penalty), found
