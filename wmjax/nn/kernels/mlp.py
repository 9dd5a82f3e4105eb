"""The transformer MLP ``GELU(x W1 + b1) W2 + b2`` with the GELU in the matmuls' epilogues.

In XLA the tanh-GELU of the hidden layer is a separate pass over a ``[M, 4D]`` tensor: written by
the first matmul, read and written by the GELU, and in the backward pass recomputed and read again
for its derivative (on an H100, IRASim-XL/2's train step spent 71 of 671 ms there, at the memory
bandwidth; benchmarks/RESULTS.md). Here two Pallas kernels take it into the matmuls:

* forward, :func:`dense_gelu`: ``pre = x W1 + b1`` and ``act = GELU(pre)`` from one tiled matmul,
  both written from the float32 accumulator (``act`` feeds the second matmul, ``pre`` is kept for
  the backward pass);
* backward, :func:`dense_gelu_backward`: ``dpre = (g W2^T) * GELU'(pre)`` from one tiled matmul,
  with ``act`` recomputed beside it (for ``dW2``).

The other four matmuls (``act W2``, ``dW2``, ``dx``, ``dW1``) stay with XLA (cuBLAS), which is as
fast as it gets for plain products. :func:`mlp` ties them together with custom VJPs; the one
activation the backward pass needs beyond the input is ``pre``, named :data:`SAVED_NAME` for remat
policies (``model.remat='dots'`` keeps it).
:func:`mlp_reference` is the same function in plain JAX.

Shapes: ``x [..., K]``, ``w1 [K, N]``, ``b1 [N]``, ``w2 [N, F]``, ``b2 [F]`` -> ``[..., F]``; the
rows ``M`` are the product of ``x``'s leading axes.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from wmjax.nn import kernels

SAVED_NAME = "mlp_pre"  # the fused MLP's residual, for jax.checkpoint_policies.save_only_these_names
_GELU_C = math.sqrt(2.0 / math.pi)
_GELU_A = 0.044715


@dataclasses.dataclass(frozen=True)
class Blocks:
  """Tile sizes of both kernels: ``rows`` x ``cols`` outputs per program, ``depth`` of the
  contraction per step; Triton's ``warps`` and pipeline ``stages``. ``cols`` and ``depth`` are
  upper bounds: each is lowered to the largest power of two that divides its dimension."""

  rows: int = 128
  cols: int = 128
  depth: int = 64
  warps: int = 8
  stages: int = 3


MIN_BLOCK = 16  # the smallest matmul tile Triton takes


def _tile(dim: int, limit: int) -> int | None:
  """The largest power of two <= ``limit`` (and >= MIN_BLOCK) that divides ``dim``."""
  size = limit
  while size >= MIN_BLOCK:
    if dim % size == 0:
      return size
    size //= 2
  return None


def supports(in_features: int, hidden: int, out_features: int, blocks: Blocks = Blocks()) -> bool:
  """Whether the kernels can tile an MLP of these widths (each a multiple of MIN_BLOCK)."""
  return all(_tile(dim, limit) is not None for dim, limit in (
      (in_features, blocks.depth), (hidden, blocks.cols), (out_features, blocks.depth)))


def _check(x, w1, b1, w2, b2) -> None:
  k = x.shape[-1]
  if w1.ndim != 2 or w2.ndim != 2 or w1.shape[0] != k or w2.shape[0] != w1.shape[1] or (
      b1.shape != (w1.shape[1],) or b2.shape != (w2.shape[1],)):
    raise ValueError(f"the MLP needs x [..., K], w1 [K, N], b1 [N], w2 [N, F], b2 [F]; got x "
                     f"{x.shape}, w1 {w1.shape}, b1 {b1.shape}, w2 {w2.shape}, b2 {b2.shape}")


# --------------------------------------------------------------------------- GELU (tanh form)


def gelu(z: jax.Array) -> jax.Array:
  """``0.5 z (1 + tanh(sqrt(2/pi) (z + 0.044715 z^3)))``, ``jax.nn.gelu(approximate=True)``."""
  return 0.5 * z * (1.0 + jnp.tanh(_GELU_C * (z + _GELU_A * z * z * z)))


def gelu_derivative(z: jax.Array) -> jax.Array:
  """``d gelu(z) / dz``."""
  t = jnp.tanh(_GELU_C * (z + _GELU_A * z * z * z))
  return 0.5 * (1.0 + t) + 0.5 * z * (1.0 - t * t) * _GELU_C * (1.0 + 3.0 * _GELU_A * z * z)


# --------------------------------------------------------------------------- kernels


def _dense_gelu_kernel(x_ref, w_ref, b_ref, *out_refs, depth: int):
  """One ``[rows, cols]`` tile: ``x [rows, K] @ w [K, cols] + b``, then GELU; ``out_refs`` are
  ``(pre, act)`` or ``(act,)``."""
  def step(i, acc):
    xs = x_ref[:, pl.ds(i * depth, depth)]
    ws = w_ref[pl.ds(i * depth, depth), :]
    return acc + jnp.dot(xs, ws, preferred_element_type=jnp.float32)

  act_ref = out_refs[-1]
  acc = jax.lax.fori_loop(0, x_ref.shape[1] // depth, step,
                          jnp.zeros(act_ref.shape, jnp.float32))
  pre = acc + b_ref[...].astype(jnp.float32)[None, :]
  if len(out_refs) == 2:
    out_refs[0][...] = pre.astype(out_refs[0].dtype)
  act_ref[...] = gelu(pre).astype(act_ref.dtype)


def _gelu_backward_kernel(g_ref, w_ref, pre_ref, dpre_ref, act_ref, *, depth: int):
  """One ``[rows, cols]`` tile: ``(g [rows, F] @ w [cols, F]^T) * GELU'(pre)`` and ``GELU(pre)``."""
  def step(i, acc):
    gs = g_ref[:, pl.ds(i * depth, depth)]
    ws = w_ref[:, pl.ds(i * depth, depth)]
    return acc + jax.lax.dot_general(gs, ws, (((1,), (1,)), ((), ())),
                                     preferred_element_type=jnp.float32)

  dact = jax.lax.fori_loop(0, g_ref.shape[1] // depth, step,
                           jnp.zeros(dpre_ref.shape, jnp.float32))
  pre = pre_ref[...].astype(jnp.float32)
  dpre = dact * gelu_derivative(pre)
  dpre_ref[...] = dpre.astype(dpre_ref.dtype)
  act_ref[...] = gelu(pre).astype(act_ref.dtype)


def _params(blocks: Blocks):
  return plgpu.CompilerParams(num_warps=blocks.warps, num_stages=blocks.stages)


def _pad_rows(a: jax.Array, rows: int) -> jax.Array:
  pad = -a.shape[0] % rows
  return a if not pad else jnp.pad(a, ((0, pad), (0, 0)))


def _dense_gelu_local(x, w, b, blocks: Blocks, interpret: bool, keep_pre: bool):
  m, k = x.shape
  n = w.shape[1]
  rows, cols, depth = blocks.rows, _tile(n, blocks.cols), _tile(k, blocks.depth)
  xp = _pad_rows(x, rows)
  grid = (xp.shape[0] // rows, n // cols)
  outputs = 2 if keep_pre else 1
  out = pl.pallas_call(
      functools.partial(_dense_gelu_kernel, depth=depth),
      out_shape=(jax.ShapeDtypeStruct((xp.shape[0], n), x.dtype),) * outputs, grid=grid,
      in_specs=[pl.BlockSpec((rows, k), lambda i, j: (i, 0)),
                pl.BlockSpec((k, cols), lambda i, j: (0, j)),
                pl.BlockSpec((cols,), lambda i, j: (j,))],
      out_specs=[pl.BlockSpec((rows, cols), lambda i, j: (i, j))] * outputs,
      compiler_params=_params(blocks), interpret=interpret, name="wmjax_dense_gelu")(xp, w, b)
  return tuple(a[:m] for a in out)


def _gelu_backward_local(g, w, pre, blocks: Blocks, interpret: bool):
  m, f = g.shape
  n = w.shape[0]
  rows, cols, depth = blocks.rows, _tile(n, blocks.cols), _tile(f, blocks.depth)
  gp, prep = _pad_rows(g, rows), _pad_rows(pre, rows)  # padded rows: g = 0, so dpre = 0
  grid = (gp.shape[0] // rows, n // cols)
  tile = pl.BlockSpec((rows, cols), lambda i, j: (i, j))
  out = jax.ShapeDtypeStruct(prep.shape, pre.dtype)
  dpre, act = pl.pallas_call(
      functools.partial(_gelu_backward_kernel, depth=depth), out_shape=(out, out), grid=grid,
      in_specs=[pl.BlockSpec((rows, f), lambda i, j: (i, 0)),
                pl.BlockSpec((cols, f), lambda i, j: (j, 0)), tile],
      out_specs=[tile, tile], compiler_params=_params(blocks), interpret=interpret,
      name="wmjax_gelu_backward")(gp, w, prep)
  return dpre[:m], act[:m]


def dense_gelu(x: jax.Array, w: jax.Array, b: jax.Array, blocks: Blocks = Blocks(),
               interpret: bool | None = None, keep_pre: bool = True):
  """``x [M, K]``, ``w [K, N]``, ``b [N]`` -> ``(pre, GELU(pre))``, each ``[M, N]`` in x's dtype,
  ``pre = x w + b`` accumulated in float32; with ``keep_pre=False`` only ``(GELU(pre),)`` (one
  write fewer, for inference). Per device under a mesh (see the package doc)."""
  interpret = kernels.interpret() if interpret is None else interpret
  local = functools.partial(_dense_gelu_local, blocks=blocks, interpret=interpret,
                            keep_pre=keep_pre)
  rows, width = kernels.split_axes(x.shape[0], w.shape[1])
  spec = kernels.P(rows, width)
  return kernels.per_device(local, in_specs=(kernels.P(rows, None), kernels.P(None, width),
                                             kernels.P(width)),
                            out_specs=(spec,) * (2 if keep_pre else 1))(x, w, b)


def dense_gelu_backward(g: jax.Array, w: jax.Array, pre: jax.Array, blocks: Blocks = Blocks(),
                        interpret: bool | None = None):
  """``g [M, F]`` (gradient of ``GELU(pre) w``), ``w [N, F]``, ``pre [M, N]`` ->
  ``(dpre, GELU(pre))``, each ``[M, N]`` in pre's dtype: ``dpre = (g w^T) * GELU'(pre)``. Per
  device under a mesh (see the package doc)."""
  interpret = kernels.interpret() if interpret is None else interpret
  local = functools.partial(_gelu_backward_local, blocks=blocks, interpret=interpret)
  rows, width = kernels.split_axes(g.shape[0], w.shape[0])
  spec = kernels.P(rows, width)
  return kernels.per_device(local, in_specs=(kernels.P(rows, None), kernels.P(width, None), spec),
                            out_specs=(spec, spec))(g, w, pre)


# --------------------------------------------------------------------------- the MLP


def mlp_reference(x, w1, b1, w2, b2):
  """``GELU(x w1 + b1) w2 + b2`` in plain JAX, in x's dtype (what ``Mlp`` computes with 'xla')."""
  h = jax.nn.gelu(jnp.dot(x, w1) + b1, approximate=True)
  return jnp.dot(h, w2) + b2


# The MLP is two custom-VJP steps so that remat policies see the hidden pre-activation as an
# ordinary value between them (a custom VJP's own residuals are recomputed under jax.checkpoint
# whatever the policy says): `_hidden` gives (pre, act) from the forward kernel; `_output` maps act
# to the output and sends the whole gradient back through pre (act is GELU(pre) by construction),
# so `_hidden`'s backward only needs dpre.


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _hidden(x, w1, b1, blocks, interpret):
  # Not differentiated (sampling): pre is never read (only _output's backward reads it), so the
  # kernel does not write it; the zeros stand in for it and are removed by XLA as unused.
  (act,) = dense_gelu(x, w1, b1, blocks, interpret, keep_pre=False)
  return jnp.zeros_like(act), act


def _hidden_forward(x, w1, b1, blocks, interpret):
  return dense_gelu(x, w1, b1, blocks, interpret), (x, w1)


def _hidden_backward(blocks, interpret, residuals, cotangents):
  x, w1 = residuals
  dpre, _ = cotangents  # act's cotangent is zero: _output routes it through pre
  dx = jnp.dot(dpre, w1.T).astype(x.dtype)
  dw1 = jnp.dot(x.T, dpre, preferred_element_type=jnp.float32).astype(w1.dtype)
  return dx, dw1, dpre.sum(0, dtype=jnp.float32).astype(w1.dtype)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5))
def _output(pre, act, w2, b2, blocks, interpret):
  return jnp.dot(act, w2) + b2


def _output_forward(pre, act, w2, b2, blocks, interpret):
  return jnp.dot(act, w2) + b2, (pre, w2)


def _output_backward(blocks, interpret, residuals, g):
  pre, w2 = residuals
  dpre, act = dense_gelu_backward(g, w2, pre, blocks, interpret)
  dw2 = jnp.dot(act.T, g, preferred_element_type=jnp.float32).astype(w2.dtype)
  return dpre, jnp.zeros_like(act), dw2, g.sum(0, dtype=jnp.float32).astype(w2.dtype)


_hidden.defvjp(_hidden_forward, _hidden_backward)
_output.defvjp(_output_forward, _output_backward)


def mlp(x: jax.Array, w1: jax.Array, b1: jax.Array, w2: jax.Array, b2: jax.Array, *,
        impl: str = "pallas", blocks: Blocks = Blocks(), interpret: bool | None = None
        ) -> jax.Array:
  """``GELU(x w1 + b1) w2 + b2``: ``x [..., K]`` -> ``[..., F]`` in x's dtype (weights cast to
  it). ``impl`` 'xla' is :func:`mlp_reference`; 'pallas' the fused kernels with the tiles
  ``blocks`` (the model's ``model.mlp_blocks``; in interpret mode off a GPU unless ``interpret``
  says otherwise); 'auto' picks by platform and falls back to 'xla' for
  widths the kernels cannot tile. The hidden pre-activation is named :data:`SAVED_NAME`."""
  _check(x, w1, b1, w2, b2)
  w1, b1, w2, b2 = (a.astype(x.dtype) for a in (w1, b1, w2, b2))
  fits = supports(x.shape[-1], w1.shape[1], w2.shape[1], blocks)
  if impl == "pallas" and not fits:
    raise ValueError(f"the fused MLP kernels tile widths that are multiples of {MIN_BLOCK}; got "
                     f"K={x.shape[-1]}, N={w1.shape[1]}, F={w2.shape[1]} (use 'xla')")
  if kernels.resolve_kernel("mlp impl", impl) == "xla" or not fits:  # 'auto' falls back
    return mlp_reference(x, w1, b1, w2, b2)
  interpret = kernels.interpret() if interpret is None else interpret
  pre, act = _hidden(x.reshape(-1, x.shape[-1]), w1, b1, blocks, interpret)
  out = _output(checkpoint_name(pre, SAVED_NAME), act, w2, b2, blocks, interpret)
  return out.reshape(x.shape[:-1] + out.shape[-1:])
