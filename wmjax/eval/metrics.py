"""Video metrics, one value per frame, over frames ``[..., H, W, C]`` (any leading axes, e.g.
``[B, T]``). Frames are uint8 or floats in [-1, 1] (the library's convention); pixel metrics see
them in [0, 1]. Callers skip the context frames, which are copies of the ground truth.

- :func:`psnr`: identical frames have infinite PSNR; it is capped at ``max_db`` (100 dB by
  default) so that means over frames stay finite. Equal to scikit-image's otherwise.
- :func:`ssim`: dm-pix's SSIM. ``window='gaussian'``: Wang et al. 2004 (11x11 Gaussian,
  sigma 1.5), as dm-pix, ``tf.image.ssim`` and scikit-image with ``gaussian_weights=True``;
  ``window='uniform'``: scikit-image's default (7x7 mean window, sample covariance), which IRASim
  uses. Colour frames average the per-channel SSIM, as scikit-image with ``channel_axis=-1``.
- :func:`grayscale`: BT.601 luma in uint8 exactly as ``cv2.cvtColor(..., COLOR_RGB2GRAY)``;
  IRASim computes PSNR and SSIM on these.
- :func:`mse` on [0, 1] pixels, :func:`latent_l2` on raw (latent) values, :func:`masked_mse` over
  user masks (WPE's arm / object MSE), :func:`square_position_error` and :func:`square_iou` for
  the gridworld.
- Fréchet distances (FID over frames, FVD over clips) from the features of a feature network:
  :class:`FeatureMoments` accumulates them, :func:`frechet_distance` compares two.
- :func:`mean_stderr` aggregates.
"""

from __future__ import annotations

import functools
import warnings

import dm_pix
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.ndimage

from wmjax.frames import to_uint8, to_unit


def grayscale(frames) -> jax.Array:
  """RGB ``[..., H, W, 3]`` -> BT.601 luma ``[..., H, W, 1]`` in [0, 1], quantised to uint8 with
  OpenCV's fixed-point arithmetic (``(4899 R + 9617 G + 1868 B + 8192) >> 14``)."""
  rgb = jnp.asarray(frames)
  if rgb.dtype != jnp.uint8:
    rgb = jnp.round(to_unit(rgb) * 255.0).astype(jnp.uint8)
  if rgb.shape[-1] != 3:
    raise ValueError(f"grayscale needs RGB frames [..., H, W, 3], got {rgb.shape}")
  weights = jnp.array([4899, 9617, 1868], jnp.int32)
  luma = ((rgb.astype(jnp.int32) * weights).sum(-1, keepdims=True) + 8192) >> 14
  return luma.astype(jnp.float32) / 255.0


def _check_pair(pred, target) -> None:
  if np.shape(pred) != np.shape(target):
    raise ValueError(f"prediction and target shapes differ: {np.shape(pred)} vs "
                     f"{np.shape(target)}")
  if np.ndim(pred) < 3:
    raise ValueError(f"frames must be [..., H, W, C], got shape {np.shape(pred)}")


def latent_l2(pred, target) -> jax.Array:
  """Mean squared difference of raw values per frame ``[...]`` (IRASim's latent L2 on latents)."""
  _check_pair(pred, target)
  diff = jnp.asarray(pred, jnp.float32) - jnp.asarray(target, jnp.float32)
  return jnp.mean(diff ** 2, axis=(-3, -2, -1))


def mse(pred, target) -> jax.Array:
  """Pixel MSE per frame on [0, 1] images."""
  _check_pair(pred, target)
  return latent_l2(to_unit(pred), to_unit(target))


def masked_mse(pred, target, mask) -> jax.Array:
  """Pixel MSE per frame over the pixels where ``mask [..., H, W]`` is true (WPE eq. 3); NaN for
  a frame whose mask is empty (aggregate with ``nanmean``)."""
  _check_pair(pred, target)
  if np.shape(mask) != np.shape(pred)[:-1]:
    raise ValueError(f"mask must be [..., H, W] = {np.shape(pred)[:-1]}, got {np.shape(mask)}")
  mask = jnp.asarray(mask, bool)
  squared = jnp.mean((to_unit(pred) - to_unit(target)) ** 2, axis=-1)
  count = mask.sum((-2, -1))
  total = jnp.where(mask, squared, 0.0).sum((-2, -1))
  return jnp.where(count > 0, total / jnp.maximum(count, 1), jnp.nan)


def psnr(pred, target, max_db: float = 100.0) -> jax.Array:
  """PSNR (dB) per frame on [0, 1] images; identical frames give ``max_db`` instead of +inf."""
  error = mse(pred, target)
  db = 10.0 * jnp.log10(1.0 / error)
  return jnp.where(error > 0, jnp.minimum(db, max_db), max_db)


_UNIFORM_WINDOW = 7


def _uniform_filter(x: jax.Array) -> jax.Array:
  """7x7 mean over ``[N, H, W, C]``, valid positions only (scikit-image crops the border)."""
  window = (1, _UNIFORM_WINDOW, _UNIFORM_WINDOW, 1)
  total = jax.lax.reduce_window(x, 0.0, jax.lax.add, window, (1, 1, 1, 1), "VALID")
  return total / _UNIFORM_WINDOW ** 2


@functools.partial(jax.jit, static_argnames="window")
def _ssim(pred: jax.Array, target: jax.Array, window: str) -> jax.Array:
  lead = pred.shape[:-3]
  a = to_unit(pred).reshape((-1,) + pred.shape[-3:])
  b = to_unit(target).reshape((-1,) + target.shape[-3:])
  if window == "gaussian":
    values = dm_pix.ssim(a, b, max_val=1.0)
  else:
    # scikit-image scales the variances by n / (n - 1) (sample covariance); in the SSIM formula
    # that equals the population form with k2 divided by sqrt(n / (n - 1)).
    n = _UNIFORM_WINDOW ** 2
    values = dm_pix.ssim(a, b, max_val=1.0, filter_fn=_uniform_filter,
                         k2=0.03 / np.sqrt(n / (n - 1)))
  return values.reshape(lead)


def ssim(pred, target, window: str = "gaussian") -> jax.Array:
  """SSIM per frame (see the module doc for ``window``); frames at least 11 (7) pixels a side."""
  _check_pair(pred, target)
  if window not in ("gaussian", "uniform"):
    raise ValueError(f"window must be 'gaussian' or 'uniform', got {window!r}")
  size = 11 if window == "gaussian" else _UNIFORM_WINDOW
  if min(np.shape(pred)[-3:-1]) < size:
    raise ValueError(f"SSIM with the {window} window needs frames of at least {size}x{size} "
                     f"pixels, got {np.shape(pred)[-3:-1]}")
  return _ssim(jnp.asarray(pred), jnp.asarray(target), window)


# ----------------------------------------------------------------------------- gridworld


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


# ----------------------------------------------------------------------------- Fréchet distances


class FeatureMoments:
  """Running mean and covariance of features ``[N, D]`` (float64 sums), fed batch by batch."""

  def __init__(self):
    self.count = 0
    self._sum: np.ndarray | None = None
    self._outer: np.ndarray | None = None

  def update(self, features) -> None:
    features = np.asarray(features, np.float64)
    if features.ndim != 2:
      raise ValueError(f"features must be [N, D], got shape {features.shape}")
    if self._sum is None:
      self._sum = np.zeros(features.shape[1])
      self._outer = np.zeros((features.shape[1],) * 2)
    elif features.shape[1] != len(self._sum):
      raise ValueError(f"features have dimension {features.shape[1]}, earlier ones "
                       f"{len(self._sum)}")
    self.count += len(features)
    self._sum += features.sum(0)
    self._outer += features.T @ features

  @property
  def mean(self) -> np.ndarray:
    return self._sum / self.count

  @property
  def covariance(self) -> np.ndarray:
    """Unbiased (``ddof=1``), as ``np.cov``."""
    if self.count < 2:
      raise ValueError(f"a covariance needs at least 2 feature vectors, got {self.count}")
    mean = self.mean
    return (self._outer - self.count * np.outer(mean, mean)) / (self.count - 1)


def frechet_distance(a: FeatureMoments, b: FeatureMoments) -> float:
  """Fréchet distance between Gaussians fitted to two feature sets:
  ``|mu_a - mu_b|^2 + tr(S_a) + tr(S_b) - 2 tr((S_a^1/2 S_b S_a^1/2)^1/2)``.

  The trace term is computed from the eigenvalues of the symmetric ``S_a^1/2 S_b S_a^1/2``, so
  it is real and stable for singular covariances (no ``sqrtm`` of a non-symmetric product).
  """
  cov_a, cov_b = a.covariance, b.covariance
  eigenvalues, eigenvectors = scipy.linalg.eigh(cov_a)
  root_a = (eigenvectors * np.sqrt(np.clip(eigenvalues, 0.0, None))) @ eigenvectors.T
  middle = root_a @ cov_b @ root_a
  trace_root = np.sqrt(np.clip(scipy.linalg.eigvalsh((middle + middle.T) / 2), 0.0, None)).sum()
  return float(np.sum((a.mean - b.mean) ** 2) + np.trace(cov_a) + np.trace(cov_b)
               - 2.0 * trace_root)


# ----------------------------------------------------------------------------- aggregation


def mean_stderr(values, axis: int | None = None) -> tuple[np.ndarray, np.ndarray]:
  """Mean and standard error (``std(ddof=1) / sqrt(n)``) ignoring NaNs; stderr is NaN for n < 2."""
  values = np.asarray(values, np.float64)
  count = np.sum(~np.isnan(values), axis=axis)
  with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
    warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices -> NaN, said above
    mean = np.nanmean(values, axis=axis)
    deviation = np.nanstd(values, axis=axis, ddof=1)
    stderr = np.where(count > 1, deviation / np.sqrt(np.maximum(count, 1)), np.nan)
  return mean, stderr
