"""Video metrics, one value per frame, over frames ``[..., H, W, C]`` (any leading axes, e.g.
``[B, T]``). Frames are uint8 or floats in [-1, 1] (the library's convention,
:mod:`wmjax.frames`), told apart by their dtype, never by their values; other dtypes are refused.
Pixel metrics see them in [0, 1]; pass [0, 1] float images as ``2 * x - 1``. Every metric is a
pure function of its inputs: it runs under ``jit``, ``vmap`` and ``grad`` (floats). Callers skip
the context frames, which are copies of the ground truth.

- :func:`psnr`: identical frames have infinite PSNR; it is capped at ``max_db`` (100 dB by
  default) so that means over frames stay finite. Equal to scikit-image's otherwise.
- :func:`ssim`: dm-pix's SSIM. ``window='gaussian'``: Wang et al. 2004 (11x11 Gaussian,
  sigma 1.5), as dm-pix, ``tf.image.ssim`` and scikit-image with ``gaussian_weights=True``;
  ``window='uniform'``: scikit-image's default (7x7 mean window, sample covariance), which IRASim
  uses. Colour frames average the per-channel SSIM, as scikit-image with ``channel_axis=-1``.
- :func:`grayscale`: BT.601 luma in uint8 exactly as ``cv2.cvtColor(..., COLOR_RGB2GRAY)``;
  IRASim computes PSNR and SSIM on these.
- :func:`mse` on [0, 1] pixels, :func:`latent_l2` on raw (latent) values, :func:`masked_mse` over
  user masks (WPE's arm / object MSE); :func:`frame_metrics` computes them all per frame, with a
  task's own (:mod:`wmjax.registry`).
- Fréchet distances (FID over frames, FVD over clips) from the features of a feature network:
  :class:`FeatureMoments` accumulates them, :func:`frechet_distance` compares two.
- :func:`mean_stderr` aggregates.
"""

from __future__ import annotations

import functools
import warnings
from typing import TYPE_CHECKING, Mapping

import dm_pix
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from wmjax.frames import to_unit

if TYPE_CHECKING:
  from wmjax.registry import FrameMetrics


def grayscale(frames) -> jax.Array:
  """RGB ``[..., H, W, 3]`` -> BT.601 luma ``[..., H, W, 1]`` in uint8, with OpenCV's
  fixed-point arithmetic (``(4899 R + 9617 G + 1868 B + 8192) >> 14``); the metrics take it as
  it is."""
  if np.shape(frames)[-1:] != (3,):
    raise ValueError(f"grayscale needs RGB frames [..., H, W, 3], got {np.shape(frames)}")
  _check_dtype(frames)
  return _luma(jnp.asarray(frames))


# The metrics check their inputs in Python and compute in one compiled program each: run op by op,
# every operation would be its own small XLA program, compiled once per shape.
@jax.jit
def _luma(frames: jax.Array) -> jax.Array:
  rgb = frames if frames.dtype == jnp.uint8 else jnp.round(to_unit(frames) * 255.0).astype(
      jnp.uint8)
  weights = jnp.array([4899, 9617, 1868], jnp.int32)
  luma = ((rgb.astype(jnp.int32) * weights).sum(-1, keepdims=True) + 8192) >> 14
  return luma.astype(jnp.uint8)


def _check_pair(pred, target) -> None:
  if np.shape(pred) != np.shape(target):
    raise ValueError(f"prediction and target shapes differ: {np.shape(pred)} vs "
                     f"{np.shape(target)}")
  if np.ndim(pred) < 3:
    raise ValueError(f"frames must be [..., H, W, C], got shape {np.shape(pred)}")


def _check_dtype(frames) -> None:
  """Pixel frames are uint8 or floats: their dtype says their range."""
  dtype = jnp.result_type(frames)
  if dtype != jnp.uint8 and not jnp.issubdtype(dtype, jnp.floating):
    raise ValueError(f"frames must be uint8 (0..255) or floats in [-1, 1], got {dtype}")


def _check_frames(pred, target) -> None:
  _check_pair(pred, target)
  _check_dtype(pred)
  _check_dtype(target)


def latent_l2(pred, target) -> jax.Array:
  """Mean squared difference of raw values per frame ``[...]`` (IRASim's latent L2 on latents)."""
  _check_pair(pred, target)
  return _mean_square(jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32))


@jax.jit
def _mean_square(a: jax.Array, b: jax.Array) -> jax.Array:
  return jnp.mean(jnp.square(a - b), axis=(-3, -2, -1))


def mse(pred, target) -> jax.Array:
  """Pixel MSE per frame of uint8 or [-1, 1] frames, measured on their [0, 1] pixels."""
  _check_frames(pred, target)
  return _pixel_mse(jnp.asarray(pred), jnp.asarray(target))


@jax.jit
def _pixel_mse(pred: jax.Array, target: jax.Array) -> jax.Array:
  return _mean_square(to_unit(pred), to_unit(target))


def masked_mse(pred, target, mask) -> jax.Array:
  """Pixel MSE per frame over the pixels where ``mask [..., H, W]`` is true (WPE eq. 3); NaN for
  a frame whose mask is empty (aggregate with ``nanmean``)."""
  _check_frames(pred, target)
  if np.shape(mask) != np.shape(pred)[:-1]:
    raise ValueError(f"mask must be [..., H, W] = {np.shape(pred)[:-1]}, got {np.shape(mask)}")
  return _masked_mse(jnp.asarray(pred), jnp.asarray(target), jnp.asarray(mask, bool))


@jax.jit
def _masked_mse(pred: jax.Array, target: jax.Array, mask: jax.Array) -> jax.Array:
  squared = jnp.mean((to_unit(pred) - to_unit(target)) ** 2, axis=-1)
  count = mask.sum((-2, -1))
  total = jnp.where(mask, squared, 0.0).sum((-2, -1))
  return jnp.where(count > 0, total / jnp.maximum(count, 1), jnp.nan)


def psnr(pred, target, max_db: float = 100.0) -> jax.Array:
  """PSNR (dB) per frame of uint8 or [-1, 1] frames, measured on their [0, 1] pixels (peak 1);
  identical frames give ``max_db`` instead of +inf."""
  _check_frames(pred, target)
  return _psnr(jnp.asarray(pred), jnp.asarray(target), max_db)


@jax.jit
def _psnr(pred: jax.Array, target: jax.Array, max_db: float) -> jax.Array:
  error = _pixel_mse(pred, target)
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
  _check_frames(pred, target)
  if window not in ("gaussian", "uniform"):
    raise ValueError(f"window must be 'gaussian' or 'uniform', got {window!r}")
  size = 11 if window == "gaussian" else _UNIFORM_WINDOW
  if min(np.shape(pred)[-3:-1]) < size:
    raise ValueError(f"SSIM with the {window} window needs frames of at least {size}x{size} "
                     f"pixels, got {np.shape(pred)[-3:-1]}")
  return _ssim(jnp.asarray(pred), jnp.asarray(target), window)


# ----------------------------------------------------------------------------- per frame

# the generic metrics of frame_metrics -> whether lower is better (for reports)
LOWER_IS_BETTER = {"mse": True, "psnr": False, "ssim": False, "gray_psnr": False,
                   "gray_ssim": False, "latent_l2": True, "masked_mse": True}


def frame_metrics(pred, truth, extras: Mapping[str, np.ndarray],
                  task: FrameMetrics | None = None) -> dict[str, np.ndarray]:
  """Per-frame metrics ``[E, T]`` of ``pred`` against ``truth`` (both ``[E, T, H, W, C]`` RGB,
  the generated frames only): MSE, PSNR, SSIM and IRASim's grayscale PSNR / SSIM (SSIM needs
  frames of at least 11 (colour) / 7 (grayscale) pixels), the masked MSE over ``extras['masks']``
  (per-frame ``[E, T, H, W]``) or the task's object masks, and the ``task``'s own metrics
  (:class:`wmjax.registry.FrameMetrics`) from the per-frame ``extras``."""
  result = {"mse": mse(pred, truth), "psnr": psnr(pred, truth)}
  h, w, c = np.shape(truth)[-3:]
  if c == 3:
    if min(h, w) >= 11:
      result["ssim"] = ssim(pred, truth, "gaussian")
    gray_pred, gray_truth = grayscale(pred), grayscale(truth)
    result["gray_psnr"] = psnr(gray_pred, gray_truth)
    if min(h, w) >= 7:
      result["gray_ssim"] = ssim(gray_pred, gray_truth, "uniform")
  masks = extras.get("masks")
  if task is not None:
    result.update(task.compute(pred, truth, extras))
    if masks is None and task.object_masks is not None:
      masks = task.object_masks(pred, truth, extras)
  if masks is not None:
    result["masked_mse"] = masked_mse(pred, truth, masks)
  return {k: np.asarray(v, np.float64) for k, v in result.items()}


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
