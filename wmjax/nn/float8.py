"""Matmuls in float8 (e4m3) for inference: :class:`Float8DotGeneral`, the ``dot_general`` that
``STDiT(fp8_matmuls=True)`` gives every linear layer of its blocks (the attention's projections
and the MLP).

Both operands of a layer's ``[M, K] x [K, N]`` matmul are scaled into e4m3's range (largest
magnitude 448) and rounded to e4m3 (3 mantissa bits: a relative rounding error of at most 1/16);
the product of the rounded operands is scaled back. On a GPU whose cuBLAS runs float8 GEMMs
(compute capability 8.9 and up: Ada, Hopper, Blackwell) XLA's GEMM rewriter makes that one
``__cublas$lt$matmul$f8`` call, at twice the bf16 peak FLOP/s; everywhere else the same numbers
are computed in the input's dtype (e4m3 values are exact in bfloat16), so a CPU shows what float8
does to a model's outputs.

The kernel gets one scale per output column, from its own largest magnitudes. The input (the
activations) gets one of two scalings:

* **dynamic** (no calibration): one scale per row (token), from the row's own largest magnitude,
  measured as the matmul runs. A token's result does not depend on the other tokens or rollouts
  of the batch, but every quantized input is read once more for its maxima, which costs about
  half of what float8 saves (benchmarks/RESULTS.md, "Rollouts in float8").
* **static** (calibrated): one fixed scale per layer, :data:`HEADROOM` times the largest magnitude
  its input reached on calibration windows (:meth:`wmjax.model.WorldModel.calibrate_float8`);
  larger inputs are clipped to it. The scaling then fuses into the kernel that makes the input.

Which one a call uses depends on the variables it is given: a :data:`COLLECTION` collection
holding every layer's ``input_amax`` makes it static; none makes it dynamic; the collection
*mutable* calibrates (dynamic scaling, and each layer's ``input_amax`` raised to the largest
magnitude seen).

For inference only: training through float8 rounding needs delayed scaling and float8 gradients,
which this module does not do (``wmjax train`` refuses ``model.fp8_matmuls``).
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

FLOAT8 = jnp.float8_e4m3fn
FLOAT8_MAX = float(jnp.finfo(FLOAT8).max)  # 448
COLLECTION = "float8"  # the variables of static scaling: each layer's calibrated input maximum
# a static scale leaves this factor of room above the calibrated maximum before it clips (one
# binade: e4m3's relative precision is the same over its normal range, 2^-6 .. 448)
HEADROOM = 2.0


def _quantize(x: jax.Array, amax: jax.Array) -> tuple[jax.Array, jax.Array]:
  """``x`` scaled so that ``amax`` (broadcastable to ``x``) maps to e4m3's largest value, clipped
  and rounded to e4m3 -> ``(x8, scale)``, ``x ~ x8 * scale`` with ``scale`` float32."""
  scale = jnp.where(amax > 0, amax / FLOAT8_MAX, 1.0)  # an all-zero row stays zero
  scaled = jnp.clip(x.astype(jnp.float32) / scale, -FLOAT8_MAX, FLOAT8_MAX)
  return scaled.astype(FLOAT8), scale


def _row_amax(x: jax.Array) -> jax.Array:
  """The largest magnitude of each row of ``x [M, K]``: ``[M, 1]`` float32."""
  return jnp.max(jnp.abs(x), axis=-1, keepdims=True).astype(jnp.float32)


class Float8DotGeneral(nn.Module):
  """A Dense layer's ``dot_general`` in float8 (see the module docstring); called as
  ``jax.lax.dot_general(lhs, rhs, dimension_numbers)`` is, with ``lhs`` the input contracted over
  its last axes and ``rhs`` the kernel over its first (other dimension numbers are refused). The
  result has ``lhs``'s dtype (or ``preferred_element_type``)."""

  @nn.compact
  def __call__(self, lhs: jax.Array, rhs: jax.Array, dimension_numbers, precision=None,
               preferred_element_type=None) -> jax.Array:
    (lhs_contracting, rhs_contracting), (lhs_batch, rhs_batch) = dimension_numbers
    k = len(lhs_contracting)
    if (lhs_batch or rhs_batch
        or tuple(np.mod(lhs_contracting, lhs.ndim)) != tuple(range(lhs.ndim - k, lhs.ndim))
        or tuple(np.mod(rhs_contracting, rhs.ndim)) != tuple(range(k))):
      raise ValueError(f"Float8DotGeneral takes a Dense layer's matmul: the input contracted "
                       f"over its last axes, the kernel over its first, no batch axes; got "
                       f"{dimension_numbers} for shapes {lhs.shape} and {rhs.shape}")
    dtype = preferred_element_type or lhs.dtype
    out_shape = lhs.shape[:lhs.ndim - k] + rhs.shape[k:]
    depth = math.prod(lhs.shape[lhs.ndim - k:])
    x = lhs.reshape(-1, depth)  # [M, K]: the rows of the input
    w = rhs.reshape(depth, -1).T  # [N, K]: the columns of the kernel
    x8, x_scale = _quantize(x, self._input_amax(x))
    w8, w_scale = _quantize(w, _row_amax(w))
    out = jax.lax.dot_general(x8.astype(dtype), w8.astype(dtype), (((1,), (1,)), ((), ())),
                              precision=precision, preferred_element_type=dtype)  # [M, N]
    return (out * (x_scale * w_scale.T).astype(dtype)).astype(dtype).reshape(out_shape)

  def _input_amax(self, x: jax.Array) -> jax.Array:
    """The magnitude the input's scale maps to e4m3's largest: each row's own (dynamic, and
    recorded when calibrating) or the calibrated maximum times :data:`HEADROOM` (static)."""
    if self.is_initializing():
      return _row_amax(x)
    if self.is_mutable_collection(COLLECTION):
      rows = _row_amax(x)
      seen = self.variable(COLLECTION, "input_amax", lambda: jnp.zeros((), jnp.float32))
      seen.value = jnp.maximum(seen.value, jnp.max(rows))
      return rows
    if self.has_variable(COLLECTION, "input_amax"):
      return HEADROOM * self.get_variable(COLLECTION, "input_amax")
    return _row_amax(x)
