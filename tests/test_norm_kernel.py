"""The fused LayerNorm -> adaLN modulate kernel (wmjax.nn.kernels.norm), in Pallas interpret mode
on the CPU: its numbers and gradients against the plain-JAX reference and under a device mesh (in
the ST-DiT: test_mlp_kernel.py::test_model_with_the_fused_kernels_equals_the_xla_model)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import tiny_config
from wmjax.nn import STDiT
from wmjax.nn.kernels import norm

pytestmark = pytest.mark.unit


def _inputs(shape, dtype=jnp.float32, seed=0):
  """x ``shape = [..., P, D]`` (mean and spread away from 0 and 1), shift, scale ``[..., 1, D]``
  and an output gradient."""
  k = jax.random.split(jax.random.key(seed), 4)
  frame = shape[:-2] + (1, shape[-1])
  x = 3.0 * jax.random.normal(k[0], shape) + 0.5
  shift, scale = jax.random.normal(k[1], frame), 0.5 * jax.random.normal(k[2], frame)
  dy = jax.random.normal(k[3], shape)
  return tuple(a.astype(dtype) for a in (x, shift, scale, dy))


def _value_and_grads(fn, x, shift, scale, dy):
  """(y, (dx, dshift, dscale)) of ``fn(x, shift, scale)`` for the output gradient ``dy``."""
  y, vjp = jax.vjp(fn, x, shift, scale)
  return y, vjp(dy)


def _pallas(x, shift, scale):
  return norm.layer_norm_modulate(x, shift, scale, impl="pallas")


def _assert_close(got, want, tol):
  """Trees of arrays equal within ``tol`` (absolute and relative), not all (nearly) zero."""
  assert jax.tree.structure(got) == jax.tree.structure(want)
  assert max(float(jnp.abs(w.astype(jnp.float32)).max()) for w in jax.tree.leaves(want)) > 0.1
  for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
    assert g.shape == w.shape and g.dtype == w.dtype
    np.testing.assert_allclose(np.asarray(g, np.float32), np.asarray(w, np.float32), atol=tol,
                               rtol=tol)


@pytest.mark.parametrize("shape,tile_elements,block_rows", [
    ((2, 3, 10, 24), norm.TILE_ELEMENTS, norm.BLOCK_ROWS),  # D not a power of two: padded, masked
    # 4-row tiles, 8-row backward blocks: 19 rows are 3 blocks of 2 tiles, the last one part padding
    ((1, 2, 19, 8), 32, 8),
])
def test_kernel_matches_reference_float32(monkeypatch, shape, tile_elements, block_rows):
  monkeypatch.setattr(norm, "TILE_ELEMENTS", tile_elements)
  monkeypatch.setattr(norm, "BLOCK_ROWS", block_rows)
  args = _inputs(shape)
  got = jax.jit(lambda *a: _value_and_grads(_pallas, *a))(*args)
  want = _value_and_grads(norm.reference, *args)
  _assert_close(got, want, 2e-5)
  # the model's own ops (impl='xla') give the same numbers in float32
  xla = _value_and_grads(lambda *a: norm.layer_norm_modulate(*a, impl="xla"), *args)
  _assert_close(xla, want, 2e-5)


def test_kernel_matches_reference_bfloat16():
  """bfloat16 in and out, float32 inside: the reference's numbers within a bfloat16 rounding."""
  args = _inputs((2, 2, 8, 48), jnp.bfloat16, seed=1)
  got = jax.jit(lambda *a: _value_and_grads(_pallas, *a))(*args)
  want = _value_and_grads(norm.reference, *args)
  _assert_close(got, want, 2e-2)


def _tiny_stdit(norm_kernel):
  config = tiny_config("irasim.py:S", f"model.norm_kernel={norm_kernel!r}")
  return STDiT(**config.model)


@pytest.mark.slow
def test_kernel_runs_once_per_device_under_a_mesh(monkeypatch):
  """XLA cannot partition a Pallas call: under a mesh the frames' batch is split over the batch
  axes with shard_map, D stays whole, and values and gradients are unchanged."""
  assert jax.device_count() == 8
  local_shapes = []
  local = norm._local
  monkeypatch.setattr(norm, "_local", lambda x, *a: local_shapes.append(x.shape) or local(x, *a))
  args = _inputs((8, 2, 4, 24))
  want = _value_and_grads(norm.reference, *args)
  mesh = jax.make_mesh((2, 2, 2), ("data", "fsdp", "tensor"),
                       axis_types=(jax.sharding.AxisType.Auto,) * 3)
  with jax.set_mesh(mesh):
    got = jax.jit(lambda *a: _value_and_grads(_pallas, *a))(*args)
  assert local_shapes == [(2, 2, 4, 24)]  # batch 8 / (data 2 x fsdp 2), D whole
  _assert_close(got, want, 2e-5)


@pytest.mark.parametrize("x_shape,frame_shape", [
    ((2, 3, 4, 8), (2, 3, 4, 8)),  # shift / scale broadcast over the rows already
    ((2, 3, 4, 8), (2, 1, 1, 8)),  # one vector per sample, not per frame
    ((2, 3, 4, 8), (2, 3, 1, 16)),  # another width
    ((8,), (1, 8)),  # no rows
])
def test_bad_shapes_are_rejected(x_shape, frame_shape):
  x, shift = jnp.zeros(x_shape), jnp.zeros(frame_shape)
  with pytest.raises(ValueError, match=r"shift and scale \[\.\.\., 1, D\]|needs x \[\.\.\., P, D\]"):
    norm.layer_norm_modulate(x, shift, shift, impl="pallas")


def test_unknown_kernel_choice_is_rejected():
  args = _inputs((1, 1, 2, 8))[:3]
  with pytest.raises(ValueError, match="model.norm_kernel must be one of"):
    norm.layer_norm_modulate(*args, impl="triton")
  with pytest.raises(ValueError, match="model.norm_kernel must be one of"):
    _tiny_stdit("fused").init(jax.random.key(0), jnp.zeros((1, 2, 8, 8, 4)), jnp.zeros((1, 2)),
                              jnp.zeros((1, 1, 7)))
