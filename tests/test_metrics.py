"""Video metrics against the reference libraries (scikit-image, dm-pix, scipy), the gridworld
square-position error, Fréchet distances and aggregation."""

import inspect
import warnings

import dm_pix
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from skimage import metrics as skm

from wmjax.eval import metrics
from wmjax.tasks.gridworld import dataset as gridworld
from wmjax.tasks.gridworld import metrics as gridworld_metrics

pytestmark = pytest.mark.unit


def _pair(shape, seed=0, noise=40):
  rng = np.random.default_rng(seed)
  a = rng.integers(0, 256, shape, dtype=np.uint8)
  b = np.clip(a.astype(int) + rng.integers(-noise, noise + 1, shape), 0, 255).astype(np.uint8)
  return a, b


def _reference(fn, a, b):
  """Apply a per-image reference over the leading axes of [E, T, H, W, C]."""
  return np.array([[fn(a[i, j], b[i, j]) for j in range(a.shape[1])] for i in range(a.shape[0])])


def _unit(x):
  return x.astype(np.float64) / 255.0


def test_psnr_equals_scikit_image_and_caps_identical_frames():
  a, b = _pair((3, 2, 20, 24, 3))
  expected = _reference(lambda x, y: skm.peak_signal_noise_ratio(_unit(x), _unit(y),
                                                                 data_range=1.0), b, a)
  np.testing.assert_allclose(metrics.psnr(b, a), expected, rtol=1e-5)
  # identical frames: scikit-image says inf; wmjax caps at max_db so that means stay finite
  np.testing.assert_array_equal(metrics.psnr(a, a), 100.0)
  np.testing.assert_array_equal(metrics.psnr(a, a, max_db=60.0), 60.0)
  # [-1, 1] floats and uint8 give the same value
  as_float = a.astype(np.float32) / 127.5 - 1.0
  np.testing.assert_allclose(metrics.psnr(b, as_float), expected, rtol=1e-4)


def test_ssim_windows_equal_scikit_image_and_dm_pix():
  a, b = _pair((2, 3, 24, 20, 3), seed=1)
  gaussian = _reference(lambda x, y: skm.structural_similarity(
      _unit(x), _unit(y), data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
      use_sample_covariance=False), a, b)
  np.testing.assert_allclose(metrics.ssim(a, b, "gaussian"), gaussian, atol=1e-5)
  pix = dm_pix.ssim(_unit(a).reshape(-1, 24, 20, 3).astype(np.float32),
                    _unit(b).reshape(-1, 24, 20, 3).astype(np.float32))
  np.testing.assert_allclose(metrics.ssim(a, b), np.reshape(pix, (2, 3)), atol=1e-6)
  uniform = _reference(lambda x, y: skm.structural_similarity(_unit(x), _unit(y), data_range=1.0,
                                                              channel_axis=-1), a, b)
  np.testing.assert_allclose(metrics.ssim(a, b, "uniform"), uniform, atol=1e-5)
  np.testing.assert_allclose(metrics.ssim(a, a), 1.0, atol=1e-6)


def test_grayscale_metrics_follow_irasim():
  """IRASim: cv2 BGR->gray on uint8 frames, PSNR with data_range 255, skimage's default SSIM."""
  a, b = _pair((2, 2, 16, 16, 3), seed=2)
  gray = np.asarray(metrics.grayscale(a))
  assert gray.dtype == np.uint8 and gray.shape == a.shape[:-1] + (1,)
  r, g, b_ = (a[..., i].astype(np.int64) for i in range(3))
  by_hand = (4899 * r + 9617 * g + 1868 * b_ + 8192) >> 14
  np.testing.assert_array_equal(gray[..., 0], by_hand)
  gray_a, gray_b = np.asarray(metrics.grayscale(a)), np.asarray(metrics.grayscale(b))
  np.testing.assert_allclose(
      metrics.ssim(gray_b, gray_a, "uniform"),
      _reference(skm.structural_similarity, gray_b[..., 0], gray_a[..., 0]), atol=1e-5)
  np.testing.assert_allclose(
      metrics.psnr(gray_b, gray_a),
      _reference(lambda x, y: skm.peak_signal_noise_ratio(x, y, data_range=255), gray_a[..., 0],
                 gray_b[..., 0]),
      rtol=1e-5)


def test_the_dtype_gives_the_range_and_values_are_never_inspected():
  """uint8 frames are 0..255, float frames [-1, 1]; other dtypes are refused, not guessed."""
  a, b = _pair((2, 16, 16, 3), seed=5)
  as_model = lambda x: x.astype(np.float32) / 127.5 - 1.0
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    np.testing.assert_allclose(metrics.psnr(as_model(a), as_model(b)), metrics.psnr(a, b),
                               rtol=1e-5)
    # [0, 1] floats are read as [-1, 1] (about 6 dB too high) without a look at their values
    unit_a, unit_b = a / np.float32(255), b / np.float32(255)
    np.testing.assert_allclose(metrics.psnr(unit_a, unit_b) - metrics.psnr(a, b), 6.0, atol=0.5)
    metrics.frame_metrics(a[None], b[None], {})
  for fn in (metrics.psnr, metrics.ssim, metrics.mse):
    with pytest.raises(ValueError, match="uint8 .* or floats in \\[-1, 1\\], got int32"):
      fn(a.astype(np.int32), b)
  with pytest.raises(ValueError, match="got int32"):
    metrics.grayscale(a.astype(np.int32))


# every public per-frame metric as f(pred, target, mask); only masked_mse reads the mask
_METRICS = {
    "psnr": lambda p, t, m: metrics.psnr(p, t),
    "ssim": lambda p, t, m: metrics.ssim(p, t, "gaussian"),
    "ssim_uniform": lambda p, t, m: metrics.ssim(p, t, "uniform"),
    "mse": lambda p, t, m: metrics.mse(p, t),
    "masked_mse": metrics.masked_mse,
    "latent_l2": lambda p, t, m: metrics.latent_l2(p, t),
    "grayscale": lambda p, t, m: metrics.grayscale(p),
}


def test_every_metric_is_pure_under_jit_vmap_and_grad():
  """The metrics check shapes and dtypes only (no value leaves the device), so they trace."""
  public = {name for name, fn in vars(metrics).items() if not name.startswith("_")
            and callable(fn) and getattr(fn, "__module__", None) == metrics.__name__
            and inspect.signature(fn).return_annotation == "jax.Array"}
  assert public <= {name.removesuffix("_uniform") for name in _METRICS}, public
  a, b = _pair((2, 3, 16, 16, 3), seed=4)
  mask = np.zeros((2, 3, 16, 16), bool)
  mask[..., 4:12, 2:9] = True
  as_model = lambda x: x.astype(np.float32) / 127.5 - 1.0
  for pred, target in ((a, b), (as_model(a), as_model(b))):
    for name, fn in _METRICS.items():
      eager = np.asarray(fn(pred, target, mask))
      for transformed in (jax.jit(fn), jax.vmap(fn)):
        np.testing.assert_allclose(transformed(pred, target, mask), eager, rtol=1e-5,
                                   err_msg=name)
  for name, fn in _METRICS.items():
    if name == "grayscale":  # uint8 luma: rounded, no gradient
      continue
    grad = jax.grad(lambda p: jnp.sum(fn(p, target, mask)))(pred)
    assert grad.shape == pred.shape and np.isfinite(grad).all() and np.abs(grad).sum() > 0, name


def test_mse_latent_l2_and_masked_mse():
  a, b = _pair((2, 3, 8, 8, 3), seed=3)
  expected = ((_unit(a) - _unit(b)) ** 2).mean((-3, -2, -1))
  np.testing.assert_allclose(metrics.mse(a, b), expected, rtol=1e-5)
  np.testing.assert_allclose(metrics.mse(a, b), _reference(
      lambda x, y: skm.mean_squared_error(_unit(x), _unit(y)), a, b), rtol=1e-5)
  x = np.random.default_rng(0).normal(size=(2, 3, 4, 4, 16)).astype(np.float32)
  np.testing.assert_allclose(metrics.latent_l2(x, 0 * x), (x ** 2).mean((-3, -2, -1)), rtol=1e-5)
  mask = np.zeros((2, 3, 8, 8), bool)
  mask[..., 2:5, 1:7] = True
  mask[1, 2] = False  # an empty mask -> NaN
  by_hand = ((_unit(a) - _unit(b)) ** 2).mean(-1)
  expected = np.array([[by_hand[i, j][mask[i, j]].mean() if mask[i, j].any() else np.nan
                        for j in range(3)] for i in range(2)])
  np.testing.assert_allclose(metrics.masked_mse(a, b, mask), expected, rtol=1e-5)
  with pytest.raises(ValueError, match="mask must be"):
    metrics.masked_mse(a, b, mask[..., :4])
  with pytest.raises(ValueError, match="shapes differ"):
    metrics.mse(a, b[:, :2])
  with pytest.raises(ValueError, match="at least 11x11"):
    metrics.ssim(a, b)


def test_frechet_distance_equals_scipy_sqrtm_formula():
  rng = np.random.default_rng(0)
  x = rng.normal(size=(400, 12))
  y = rng.normal(size=(300, 12)) @ rng.normal(size=(12, 12)) * 0.3 + 0.7
  a, b = metrics.FeatureMoments(), metrics.FeatureMoments()
  for chunk in np.array_split(x, 3):  # fed batch by batch
    a.update(chunk)
  b.update(y)
  np.testing.assert_allclose(a.covariance, np.cov(x, rowvar=False), rtol=1e-10)
  s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
  expected = (np.sum((x.mean(0) - y.mean(0)) ** 2)
              + np.trace(s1 + s2 - 2 * scipy.linalg.sqrtm(s1 @ s2).real))
  np.testing.assert_allclose(metrics.frechet_distance(a, b), expected, rtol=1e-8)
  assert abs(metrics.frechet_distance(a, a)) < 1e-8
  # rank-deficient covariances (fewer samples than dimensions) stay finite and non-negative
  c, d = metrics.FeatureMoments(), metrics.FeatureMoments()
  c.update(rng.normal(size=(5, 12)))
  d.update(rng.normal(size=(5, 12)))
  assert np.isfinite(metrics.frechet_distance(c, d)) and metrics.frechet_distance(c, d) > 0


def test_mean_stderr():
  mean, stderr = metrics.mean_stderr([1.0, 2.0, 3.0, np.nan])
  assert mean == 2.0 and abs(stderr - 1.0 / np.sqrt(3)) < 1e-12
  mean, stderr = metrics.mean_stderr([[1.0, np.nan], [3.0, np.nan]], axis=0)
  np.testing.assert_allclose(mean, [2.0, np.nan])
  assert np.isnan(stderr[1]) and abs(stderr[0] - 1.0) < 1e-12
  assert np.isnan(metrics.mean_stderr([5.0])[1])


def test_square_positions_are_recovered_from_rendered_frames():
  config = gridworld.GridworldConfig(num_squares=3, image_size=32, square_size=4)
  centres = np.array([[4.0, 6.0], [20.0, 10.0], [12.0, 28.0]], np.float32)
  frame = gridworld.render(centres, config)
  found_centres, found = gridworld_metrics.color_centroids(frame, gridworld.COLORS[:3])
  assert found.all()
  np.testing.assert_allclose(found_centres, centres, atol=1e-6)
  error, _ = gridworld_metrics.square_position_error(frame[None], centres[None] + [3.0, 4.0],
                                           gridworld.COLORS[:3], missing_penalty=16.0)
  np.testing.assert_allclose(error, 5.0, atol=1e-6)
  empty = np.zeros_like(frame)
  error, found = gridworld_metrics.square_position_error(empty, centres, gridworld.COLORS[:3], 16.0)
  assert not found.any() and (error == 16.0).all()


def test_square_iou_on_hand_made_frames():
  config = gridworld.GridworldConfig(num_squares=2, image_size=16, square_size=4)
  colors = gridworld.COLORS[:2]
  truth = gridworld.render(np.array([[4.0, 4.0], [11.0, 11.0]], np.float32), config)
  iou, one = gridworld_metrics.square_iou(truth, truth, colors)
  np.testing.assert_array_equal(iou, [1.0, 1.0])
  assert one.all()
  # square 0 shifted by one pixel: 12 of 16 pixels shared, union 20
  shifted = gridworld.render(np.array([[4.0, 5.0], [11.0, 11.0]], np.float32), config)
  iou, one = gridworld_metrics.square_iou(shifted, truth, colors)
  np.testing.assert_allclose(iou, [12 / 20, 1.0])
  assert one.all()
  # square 1 fragmented: its centroid stays, every other pixel of it goes black
  fragmented = truth.copy()
  fragmented[9:13, 9:13][np.indices((4, 4)).sum(0) % 2 == 1] = 0
  iou, one = gridworld_metrics.square_iou(fragmented, truth, colors)
  np.testing.assert_allclose(iou, [1.0, 0.5])
  np.testing.assert_array_equal(one, [True, False])
  # square 0 missing; a leading batch axis is kept
  missing = truth.copy()
  missing[2:6, 2:6] = 0
  iou, one = gridworld_metrics.square_iou(np.stack([missing, truth]), np.stack([truth, truth]), colors)
  np.testing.assert_allclose(iou, [[0.0, 1.0], [1.0, 1.0]])
  np.testing.assert_array_equal(one, [[False, True], [True, True]])
