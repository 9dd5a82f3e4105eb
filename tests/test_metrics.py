"""Video metrics used during training: PSNR and the gridworld square-position error."""

import numpy as np

from wmjax.data import gridworld
from wmjax.eval import metrics


def test_psnr_values():
  a = np.zeros((2, 4, 4, 3), np.float32) - 1.0  # black in [-1, 1]
  b = a.copy()
  b[0] += 0.2  # +0.1 in [0, 1] units -> MSE 0.01 -> 20 dB
  np.testing.assert_allclose(metrics.psnr(b, a), [20.0, 100.0], rtol=1e-6)  # identical: capped
  as_uint8 = np.round((b + 1) * 127.5).astype(np.uint8)
  assert abs(metrics.psnr(as_uint8, a)[0] - 20.0) < 0.2


def test_square_positions_are_recovered_from_rendered_frames():
  config = gridworld.GridworldConfig(num_squares=3, image_size=32, square_size=4)
  centres = np.array([[4.0, 6.0], [20.0, 10.0], [12.0, 28.0]], np.float32)
  frame = gridworld.render(centres, config)
  found_centres, found = metrics.color_centroids(frame, gridworld.COLORS[:3])
  assert found.all()
  np.testing.assert_allclose(found_centres, centres, atol=1e-6)
  error, _ = metrics.square_position_error(frame[None], centres[None] + [3.0, 4.0],
                                           gridworld.COLORS[:3], missing_penalty=16.0)
  np.testing.assert_allclose(error, 5.0, atol=1e-6)
  empty = np.zeros_like(frame)
  error, found = metrics.square_position_error(empty, centres, gridworld.COLORS[:3], 16.0)
  assert not found.any() and (error == 16.0).all()
