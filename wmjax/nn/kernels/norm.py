"""LayerNorm -> adaLN modulate in one pass: ``LN(x) * (1 + scale) + shift``.

``x [..., P, D]`` holds the ``P`` rows (patches) of every frame; ``shift`` and ``scale``
``[..., 1, D]`` hold one vector per frame, applied to each of its rows. The LayerNorm has no affine
parameters (eps :data:`EPS`) and computes in float32.

``impl`` (``model.norm_kernel``, see :mod:`wmjax.nn.kernels`):

``xla``     :func:`layer_norm` then :func:`modulate`, the model's ops as they always were: the
            normalised rows are cast to ``x.dtype`` before they are modulated.
``pallas``  a Pallas kernel that reads each row once and writes the modulated row, computing in
            float32 throughout (the numbers of :func:`reference`). Its backward pass is a second
            kernel that reads ``x`` and the output gradient once and writes ``dx`` and, per block
            of rows, partial sums of the shift and scale gradients, which XLA adds up (no
            atomics: the result does not depend on the order the blocks run in).

On the GPU the kernels load rows ``D`` wide padded to a power of two (Triton's tile sizes) and
mask the padding.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from wmjax.nn import kernels

EPS = 1e-6
TILE_ELEMENTS = 8192  # float32 elements of one (rows x padded D) tile a kernel holds at once
BLOCK_ROWS = 64  # rows per backward program, whose shift / scale gradients it sums


def _standardise(x: jax.Array) -> jax.Array:
  """``(x - mean) / sqrt(var + EPS)`` over the last axis, in float32."""
  x32 = x.astype(jnp.float32)
  mean = x32.mean(-1, keepdims=True)
  var = jnp.square(x32 - mean).mean(-1, keepdims=True)
  return (x32 - mean) * jax.lax.rsqrt(var + EPS)


def layer_norm(x: jax.Array) -> jax.Array:
  """LayerNorm without affine parameters (eps 1e-6), computed in float32."""
  return _standardise(x).astype(x.dtype)


def modulate(x: jax.Array, shift: jax.Array, scale: jax.Array) -> jax.Array:
  return x * (1 + scale) + shift


def reference(x: jax.Array, shift: jax.Array, scale: jax.Array) -> jax.Array:
  """What the kernel computes, in plain JAX: LN and modulate in float32, cast once at the end."""
  dtype = jnp.result_type(x, shift, scale)
  xhat = _standardise(x)
  return (xhat * (1 + scale.astype(jnp.float32)) + shift.astype(jnp.float32)).astype(dtype)


def layer_norm_modulate(x: jax.Array, shift: jax.Array, scale: jax.Array, *,
                        impl: str = "xla") -> jax.Array:
  """``x [..., P, D]``, ``shift, scale [..., 1, D]`` (one vector per frame) -> ``[..., P, D]``."""
  _check_shapes(x, shift, scale)
  if kernels.resolve_kernel("model.norm_kernel", impl) == "xla":
    return modulate(layer_norm(x), shift, scale)
  return _per_device(x, shift, scale)


def _check_shapes(x, shift, scale) -> None:
  if x.ndim < 2:
    raise ValueError(f"layer_norm_modulate needs x [..., P, D], got shape {tuple(x.shape)}")
  want = tuple(x.shape[:-2]) + (1, x.shape[-1])
  if tuple(shift.shape) != want or tuple(scale.shape) != want:
    raise ValueError(f"layer_norm_modulate needs shift and scale [..., 1, D] = {want} for x "
                     f"{tuple(x.shape)}, got shift {tuple(shift.shape)}, scale "
                     f"{tuple(scale.shape)}")


def _per_device(x, shift, scale):
  """The kernel once per device under a mesh (XLA cannot partition a Pallas call): the leading
  axis split over the batch axes that divide it, every other axis (D too) whole."""
  batch, _ = kernels.split_axes(x.shape[0]) if x.ndim > 2 else (None, None)  # [P, D]: one frame
  spec = kernels.P(batch)
  return kernels.per_device(_local, in_specs=(spec,) * 3, out_specs=spec)(x, shift, scale)


def _local(x, shift, scale):
  """Frames flattened: ``x [F, P, D]``, ``shift, scale [F, D]`` for the kernels."""
  p, d = x.shape[-2:]
  frames = math.prod(x.shape[:-2])
  dtype = jnp.result_type(x, shift, scale)  # the output's, as modulate's
  shift, scale = (a.reshape(frames, d).astype(dtype) for a in (shift, scale))
  return _fused(x.reshape(frames, p, d), shift, scale).reshape(x.shape)


@jax.custom_vjp
def _fused(x, shift, scale):
  return _forward(x, shift, scale)[0]


def _fused_fwd(x, shift, scale):
  y, mean, rstd = _forward(x, shift, scale)
  return y, (x, scale, mean, rstd)


def _fused_bwd(residuals, dy):
  x, scale, mean, rstd = residuals
  dx, dshift, dscale = _backward(x, scale, mean, rstd, dy)
  return dx, dshift.sum(1).astype(scale.dtype), dscale.sum(1).astype(scale.dtype)


_fused.defvjp(_fused_fwd, _fused_bwd)


# --------------------------------------------------------------------------- kernels


def _tile_rows(p: int, d: int) -> int:
  """Rows of one tile: a power of two, at most ``P`` rounded up, about TILE_ELEMENTS in all."""
  return max(1, min(TILE_ELEMENTS // pl.next_power_of_2(d), pl.next_power_of_2(p)))


def _compiler_params(d: int) -> plgpu.CompilerParams:
  return plgpu.CompilerParams(num_warps=8 if pl.next_power_of_2(d) >= 2048 else 4, num_stages=1)


def _load(ref, rows, cols, mask):
  """``ref[rows, cols]`` in float32, zero where ``mask`` is False (padding, rows past ``P``)."""
  return plgpu.load(ref.at[rows, cols], mask=mask, other=0.0).astype(jnp.float32)


def _tile_masks(first_row, tile: int, p: int, d: int):
  """Masks of the rows ``first_row ..`` of a tile: rows ``[tile]`` (those before ``P``), columns
  ``[Dp]`` (those before ``D``) and elements ``[tile, Dp]``."""
  row_ok = first_row + jnp.arange(tile) < p
  col_ok = jnp.arange(pl.next_power_of_2(d)) < d
  return row_ok, col_ok, row_ok[:, None] & col_ok[None, :]


def _load_frame(ref, cols, col_ok):
  """A per-frame vector ``ref [D]`` -> ``[1, Dp]`` float32, zero in the padding."""
  return plgpu.load(ref.at[cols], mask=col_ok, other=0.0).astype(jnp.float32)[None]


def _normalise(x, mask, d: int):
  """``x [tile, Dp]`` (zero where masked) -> ``(xhat, mean [tile], rstd [tile])``."""
  mean = x.sum(1) / d
  centred = jnp.where(mask, x - mean[:, None], 0.0)
  rstd = jax.lax.rsqrt((centred * centred).sum(1) / d + EPS)
  return centred * rstd[:, None], mean, rstd


def _forward_kernel(x_ref, shift_ref, scale_ref, y_ref, mean_ref, rstd_ref, *, p: int, d: int):
  """One tile of rows of one frame: ``x_ref [tile, D]``, ``shift_ref, scale_ref [D]``."""
  tile = x_ref.shape[0]
  row_ok, col_ok, mask = _tile_masks(pl.program_id(1) * tile, tile, p, d)
  rows, cols = pl.ds(0, tile), pl.ds(0, pl.next_power_of_2(d))
  xhat, mean, rstd = _normalise(_load(x_ref, rows, cols, mask), mask, d)
  y = xhat * (1 + _load_frame(scale_ref, cols, col_ok)) + _load_frame(shift_ref, cols, col_ok)
  plgpu.store(y_ref.at[rows, cols], y.astype(y_ref.dtype), mask=mask)
  plgpu.store(mean_ref.at[rows], mean, mask=row_ok)
  plgpu.store(rstd_ref.at[rows], rstd, mask=row_ok)


def _forward(x, shift, scale):
  """``x [F, P, D]``, ``shift, scale [F, D]`` -> ``y [F, P, D]`` (in shift's dtype), ``mean,
  rstd [F, P]`` float32."""
  f, p, d = x.shape
  tile = _tile_rows(p, d)
  rows = pl.BlockSpec((None, tile, d), lambda i, j: (i, j, 0))
  frame = pl.BlockSpec((None, d), lambda i, j: (i, 0))
  stats = pl.BlockSpec((None, tile), lambda i, j: (i, j))
  return pl.pallas_call(
      functools.partial(_forward_kernel, p=p, d=d),
      grid=(f, pl.cdiv(p, tile)),
      in_specs=[rows, frame, frame],
      out_specs=[rows, stats, stats],
      out_shape=[jax.ShapeDtypeStruct(x.shape, shift.dtype),
                 jax.ShapeDtypeStruct((f, p), jnp.float32),
                 jax.ShapeDtypeStruct((f, p), jnp.float32)],
      compiler_params=_compiler_params(d),
      interpret=kernels.interpret(),
      name="wmjax_layer_norm_modulate",
  )(x, shift, scale)


def _backward_kernel(x_ref, scale_ref, mean_ref, rstd_ref, dy_ref, dx_ref, dshift_ref, dscale_ref,
                     *, tile: int, p: int, d: int):
  """One block of rows of one frame, a tile at a time: ``x_ref, dy_ref [block, D]``,
  ``mean_ref, rstd_ref [block]``, ``scale_ref [D]``; writes ``dx_ref [block, D]`` and the block's
  sums of the shift and scale gradients, ``dshift_ref, dscale_ref [D]``."""
  block = x_ref.shape[0]
  cols = pl.ds(0, pl.next_power_of_2(d))
  col_ok = jnp.arange(cols.size) < d
  gain = 1 + _load_frame(scale_ref, cols, col_ok)  # [1, Dp]
  block_start = pl.program_id(1) * block  # (read outside the loop: interpret mode needs that)

  def step(i, sums):
    first = i * tile
    row_ok, _, mask = _tile_masks(block_start + first, tile, p, d)
    rows = pl.ds(first, tile)
    mean = plgpu.load(mean_ref.at[rows], mask=row_ok, other=0.0)[:, None]
    rstd = plgpu.load(rstd_ref.at[rows], mask=row_ok, other=0.0)[:, None]
    xhat = jnp.where(mask, (_load(x_ref, rows, cols, mask) - mean) * rstd, 0.0)
    dy = _load(dy_ref, rows, cols, mask)
    dxhat = dy * gain
    # d/dx of (x - mean) * rstd: remove the gradient's mean and its component along xhat
    dx = (dxhat - dxhat.sum(1, keepdims=True) / d
          - xhat * (dxhat * xhat).sum(1, keepdims=True) / d) * rstd
    plgpu.store(dx_ref.at[rows, cols], dx.astype(dx_ref.dtype), mask=mask)
    return sums[0] + dy.sum(0), sums[1] + (dy * xhat).sum(0)

  zeros = jnp.zeros((cols.size,), jnp.float32)
  dshift, dscale = jax.lax.fori_loop(0, block // tile, step, (zeros, zeros))
  plgpu.store(dshift_ref.at[cols], dshift, mask=col_ok)
  plgpu.store(dscale_ref.at[cols], dscale, mask=col_ok)


def _backward(x, scale, mean, rstd, dy):
  """``x, dy [F, P, D]``, ``scale [F, D]``, ``mean, rstd [F, P]`` -> ``dx [F, P, D]`` (x.dtype)
  and the shift and scale gradients summed per block of rows, ``[F, blocks, D]`` float32."""
  f, p, d = x.shape
  tile = _tile_rows(p, d)
  block = max(tile, min(BLOCK_ROWS, pl.next_power_of_2(p)))
  blocks = pl.cdiv(p, block)
  rows = pl.BlockSpec((None, block, d), lambda i, j: (i, j, 0))
  frame = pl.BlockSpec((None, d), lambda i, j: (i, 0))
  stats = pl.BlockSpec((None, block), lambda i, j: (i, j))
  partial = pl.BlockSpec((None, None, d), lambda i, j: (i, j, 0))
  partial_shape = jax.ShapeDtypeStruct((f, blocks, d), jnp.float32)
  return pl.pallas_call(
      functools.partial(_backward_kernel, tile=tile, p=p, d=d),
      grid=(f, blocks),
      in_specs=[rows, frame, stats, stats, rows],
      out_specs=[rows, partial, partial],
      out_shape=[jax.ShapeDtypeStruct(x.shape, x.dtype), partial_shape, partial_shape],
      compiler_params=_compiler_params(d),
      interpret=kernels.interpret(),
      name="wmjax_layer_norm_modulate_backward",
  )(x, scale, mean, rstd, dy)
