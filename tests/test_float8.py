"""Float8 matmuls for inference (wmjax.nn.float8, model.fp8_matmuls): the rounding and scaling a
float8 GEMM does, a calibrated network that follows the full-precision one, and a trainer that
refuses it."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_dtypes
import numpy as np
import pytest

from conftest import TRAIN_OVERRIDES, tiny_config
from wmjax.config import ConfigError
from wmjax.diffusion import objectives
from wmjax.diffusion.sampling import SamplerConfig
from wmjax.model import WorldModel
from wmjax.nn import STDiT, float8
from wmjax.parallel import make_mesh
from wmjax.train.step import ShardedTrainer

pytestmark = pytest.mark.unit


def _float8_reference(x, w, x_amax):
  """numpy: x [M, K] scaled by ``x_amax`` [M, 1] and w [K, N] per column, each rounded to e4m3
  (ml_dtypes), multiplied in float64 and scaled back."""
  w_amax = np.abs(w).max(0, keepdims=True)
  x8 = np.clip(x / (x_amax / 448), -448, 448).astype(ml_dtypes.float8_e4m3fn).astype(np.float64)
  w8 = (w / (w_amax / 448)).astype(ml_dtypes.float8_e4m3fn).astype(np.float64)
  return (x8 @ w8) * (x_amax / 448) * (w_amax / 448)


def _dense(features=24):
  return nn.Dense(features, use_bias=False, dot_general=float8.Float8DotGeneral())


def test_float8_matmul_rounds_each_row_and_column_to_e4m3_and_scales_back():
  x = np.asarray(jax.random.normal(jax.random.key(0), (6, 40)), np.float64)
  x[2] *= 1e3  # one loud token
  layer = _dense()
  params = layer.init(jax.random.key(1), jnp.asarray(x, jnp.float32))
  w = np.asarray(params["params"]["kernel"], np.float64)
  out = np.asarray(layer.apply(params, jnp.asarray(x, jnp.float32)))
  reference = _float8_reference(x, w, np.abs(x).max(1, keepdims=True))
  np.testing.assert_allclose(out, reference, rtol=1e-4, atol=1e-4 * np.abs(reference).max())
  exact = x @ w
  error = np.abs(out - exact).max() / np.abs(exact).max()
  assert 1e-4 < error < 0.1  # rounded, and by e4m3's 3 mantissa bits only
  # dynamic scaling is per row: a token's result ignores how loud the others are
  quiet = np.asarray(layer.apply(params, jnp.asarray(np.delete(x, 2, 0), jnp.float32)))
  np.testing.assert_array_equal(quiet, np.delete(out, 2, 0))


def test_float8_matmul_refuses_what_is_not_a_dense_layers_matmul():
  op = float8.Float8DotGeneral()
  x = jnp.ones((2, 3, 4))
  with pytest.raises(ValueError, match="the input contracted over its last axes"):
    op.apply({}, x, jnp.ones((2, 4, 5)), (((2,), (1,)), ((0,), (0,))))
  with pytest.raises(ValueError, match="the input contracted over its last axes"):
    op.apply({}, x, jnp.ones((3, 5)), (((1,), (0,)), ((), ())))


def _world_model(fp8: bool, scan: bool) -> WorldModel:
  network = STDiT(in_channels=4, patch_size=2, hidden_size=32, depth=4, num_heads=2,
                  num_frames=4, action_dim=3, scan_layers=scan, fp8_matmuls=fp8)
  return WorldModel(network, objectives.make_process("gaussian", "linear", 1000, "eps"),
                    SamplerConfig(sampler="ddim", num_steps=2))


def test_calibrated_float8_network_follows_the_full_precision_one():
  full, fp8 = _world_model(False, scan=True), _world_model(True, scan=True)
  # random weights everywhere (adaLN's zero init would leave the blocks out)
  params = jax.tree.map(lambda p: p + 0.05 * jax.random.normal(jax.random.key(3), p.shape),
                        nn.unbox(full.init(jax.random.key(0), (8, 8, 4), 4)))
  abstract = jax.eval_shape(lambda: nn.unbox(fp8.init(jax.random.key(0), (8, 8, 4), 4)))
  assert jax.tree.structure(abstract) == jax.tree.structure(params)  # no parameters added
  windows = jax.random.normal(jax.random.key(1), (3, 4, 8, 8, 4))
  actions = jax.random.normal(jax.random.key(2), (3, 3, 3))
  calibrated = fp8.calibrate_float8(params, windows, actions, jax.random.key(4))
  maxima = jax.tree.leaves(calibrated[float8.COLLECTION])
  # 2 layers x (spatial, temporal) x (q/k/v, out, fc1, fc2): each layer's input maximum
  assert sum(np.size(m) for m in maxima) == 2 * 2 * 4 and min(np.min(m) for m in maxima) > 0
  unrolled = _world_model(True, scan=False)
  unrolled_params = jax.eval_shape(lambda: nn.unbox(unrolled.init(jax.random.key(0), (8, 8, 4))))
  unrolled_maxima = jax.eval_shape(lambda p: unrolled.calibrate_float8(
      p, windows, actions, jax.random.key(4))[float8.COLLECTION], unrolled_params)
  assert [m.shape for m in jax.tree.leaves(unrolled_maxima)] == [()] * (2 * 2 * 4)
  with pytest.raises(ValueError, match="model.fp8_matmuls=True"):
    full.calibrate_float8(params, windows, actions, jax.random.key(4))

  x = jax.random.normal(jax.random.key(5), (3, 4, 8, 8, 4))
  levels, mask = jnp.full((3, 4), 500), jnp.ones((3, 3), bool)
  full_denoise, denoise = (jax.jit(model.denoise) for model in (full, fp8))
  reference = full_denoise(params, x, levels, actions, mask)
  relative = lambda y: float(jnp.linalg.norm(y - reference) / jnp.linalg.norm(reference))
  static = denoise(calibrated, x, levels, actions, mask)
  dynamic = denoise(params, x, levels, actions, mask)
  assert 1e-4 < relative(static) < 0.03 and 1e-4 < relative(dynamic) < 0.03
  assert not np.array_equal(np.asarray(static), np.asarray(dynamic))  # two scalings
  # inputs far beyond the calibration are clipped, not overflowed to NaN
  assert np.isfinite(np.asarray(denoise(calibrated, 1e3 * x, levels, actions, mask))).all()


def test_training_refuses_float8_matmuls():
  config = tiny_config("gridworld.py", *TRAIN_OVERRIDES, "model.fp8_matmuls=True")
  with pytest.raises(ConfigError, match="model.fp8_matmuls=True is for inference"):
    ShardedTrainer(WorldModel.from_config(config), config, make_mesh((1, 1, 1),
                                                                     jax.devices()[:1]),
                   (8, 8, 3), 4)
