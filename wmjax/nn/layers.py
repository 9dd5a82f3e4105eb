"""Building blocks of the ST-DiT: embeddings, patchify, attention, MLP and adaLN-Zero blocks.

Every parameter carries logical axis names (``nn.with_logical_partitioning``) so that
``wmjax.parallel`` can map them onto a device mesh by rules. The names used:

  embed       model width D
  mlp         hidden width of an MLP (4D in a block, D in the embedders)
  heads, kv   attention heads and head dimension
  modulation  the 6D (block) or 2D (final layer) adaLN outputs
  freq        timestep frequency features
  action      raw action dimension
  patch       patch pixels (p * p * channels)
  layers      stacked layers when the blocks are scanned

Activations are ``[B, T, P, D]``: batch, frames, patches of one frame, width. They are
constrained at block boundaries to the logical axes :data:`ACTIVATION_AXES` (``act_batch``,
``act_frames``, ``act_patches``, ``act_embed``), which ``wmjax.parallel.LOGICAL_RULES`` maps onto
the trainer's mesh; off that mesh (inference) the constraint does nothing.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from einops import rearrange
from jax.ad_checkpoint import checkpoint_name

from wmjax.nn.attention import attend
from wmjax.nn.float8 import Float8DotGeneral
from wmjax.parallel import LOGICAL_RULES, MESH_AXES

Dtype = Any

_xavier = nn.initializers.xavier_uniform()
_zeros = nn.initializers.zeros


def logical(init: Callable, *names: str | None) -> Callable:
  """An initializer whose parameter is annotated with logical axis names."""
  return nn.with_logical_partitioning(init, names)


ACTIVATION_AXES = ("act_batch", "act_frames", "act_patches", "act_embed")


def constrain(x: jax.Array) -> jax.Array:
  """``x [B, T, P, D]`` laid out by :data:`ACTIVATION_AXES` under :data:`LOGICAL_RULES` when
  traced on a ``(data, fsdp, tensor)`` mesh (the trainer's); unchanged otherwise."""
  mesh = jax.sharding.get_abstract_mesh()
  if mesh.empty or not set(MESH_AXES) <= set(mesh.axis_names):
    return x
  return nn.with_logical_constraint(x, ACTIVATION_AXES, rules=LOGICAL_RULES)


# --------------------------------------------------------------------------- positions


def sincos_1d(dim: int, positions: np.ndarray) -> np.ndarray:
  """Sin-cos embedding of positions ``[M]`` -> ``[M, dim]`` (sines first, then cosines)."""
  if dim % 2:
    raise ValueError(f"sin-cos embedding needs an even width, got {dim}")
  omega = 1.0 / 10000 ** (np.arange(dim // 2, dtype=np.float64) / (dim / 2))
  angles = np.asarray(positions, np.float64).reshape(-1)[:, None] * omega[None]
  return np.concatenate([np.sin(angles), np.cos(angles)], axis=1).astype(np.float32)


def sincos_2d(dim: int, grid_h: int, grid_w: int, columns_first: bool = False) -> np.ndarray:
  """Fixed 2-D sin-cos positions of a (possibly non-square) patch grid -> ``[grid_h*grid_w, dim]``.

  Half of the width encodes the row, half the column, row-major patch order. The first half is
  the row, or with ``columns_first`` the column, as in the MAE / DiT / IRASim code, whose
  ``np.meshgrid(grid_w, grid_h)`` puts the column first.
  """
  if dim % 4:
    raise ValueError(f"2-D sin-cos embedding needs a width divisible by 4, got {dim}")
  rows, cols = np.meshgrid(np.arange(grid_h), np.arange(grid_w), indexing="ij")
  halves = [sincos_1d(dim // 2, rows.reshape(-1)), sincos_1d(dim // 2, cols.reshape(-1))]
  return np.concatenate(halves[::-1] if columns_first else halves, axis=1)


def timestep_features(t: jax.Array, dim: int = 256, max_period: float = 10000.0) -> jax.Array:
  """DiT sinusoidal timestep features: ``t [...]`` (may be fractional) -> ``[..., dim]``."""
  half = dim // 2
  freqs = jnp.exp(-math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / half)
  args = t.astype(jnp.float32)[..., None] * freqs
  return jnp.concatenate([jnp.cos(args), jnp.sin(args)], axis=-1)


def rope(x: jax.Array, positions: jax.Array, base: float = 10000.0) -> jax.Array:
  """Rotary position embedding over the last axis of ``x [N, L, ..., H, d]`` (its tokens at
  positions along axis 1; the axes between are batch axes, as the patches of temporal attention).

  ``positions [L]`` rotates the whole head dimension by one position per token; ``positions
  [L, k]`` (e.g. the (row, column) of a patch) is axial: the head dimension splits into ``k`` equal
  parts and part ``i`` is rotated by ``positions[:, i]``, so a query-key score depends only on
  the offset between the two tokens along every axis.
  """
  if positions.ndim == 2:
    axes = positions.shape[1]
    if x.shape[-1] % (2 * axes):
      raise ValueError(f"axial RoPE over {axes} axes needs a head dimension divisible by "
                       f"{2 * axes}, got {x.shape[-1]}")
    parts = jnp.split(x, axes, axis=-1)
    return jnp.concatenate([rope(part, positions[:, i], base) for i, part in enumerate(parts)],
                           axis=-1)
  d = x.shape[-1]
  if d % 2:
    raise ValueError(f"RoPE needs an even head dimension, got {d}")
  inv_freq = 1.0 / base ** (jnp.arange(0, d, 2, dtype=jnp.float32) / d)
  angles = positions.astype(jnp.float32)[:, None] * inv_freq  # [L, d/2]
  angles = angles.reshape((1, x.shape[1]) + (1,) * (x.ndim - 3) + (d // 2,))
  cos, sin = jnp.cos(angles), jnp.sin(angles)
  x1, x2 = jnp.split(x.astype(jnp.float32), 2, axis=-1)
  return jnp.concatenate([x1 * cos - x2 * sin, x1 * sin + x2 * cos], axis=-1).astype(x.dtype)


# --------------------------------------------------------------------------- embedders


class TimestepEmbedder(nn.Module):
  """Noise level -> conditioning vector: sinusoid(256) -> Linear -> SiLU -> Linear.

  ``t [...]`` -> ``[..., D]``.
  """

  hidden_size: int
  frequency_dim: int = 256
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, t: jax.Array) -> jax.Array:
    init = nn.initializers.normal(0.02)
    h = timestep_features(t, self.frequency_dim)
    h = nn.Dense(self.hidden_size, dtype=self.dtype, kernel_init=logical(init, "freq", "mlp"),
                 bias_init=logical(_zeros, "mlp"), name="fc1")(h)
    h = nn.silu(h)
    return nn.Dense(self.hidden_size, dtype=self.dtype, kernel_init=logical(init, "mlp", "embed"),
                    bias_init=logical(_zeros, "embed"), name="fc2")(h)


class ActionEmbedder(nn.Module):
  """Raw action vector -> conditioning vector ``[..., A] -> [..., D]``.

  ``hidden_ratio == 0`` is one linear map (WPE); otherwise an MLP
  ``Linear(A, ratio*D) -> GELU-tanh -> Linear(ratio*D, D)`` (IRASim). With ``fourier_features
  = K > 0`` each action number ``a`` first becomes ``[a, sin(2^k pi a), cos(2^k pi a)]`` for
  ``k < K`` (NeRF's positional encoding, Tancik et al. 2020), ``[..., A] -> [..., A (1 + 2K)]``:
  a linear map of those can change sharply with ``a``, as the next frame does where an action
  crosses a rounding boundary of the pixel grid, which a linear map of ``a`` alone cannot.
  """

  hidden_size: int
  hidden_ratio: int = 0
  fourier_features: int = 0
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, actions: jax.Array) -> jax.Array:
    if self.fourier_features:
      actions = fourier_encode(actions, self.fourier_features)
    if self.hidden_ratio == 0:
      return nn.Dense(self.hidden_size, dtype=self.dtype,
                      kernel_init=logical(_xavier, "action", "embed"),
                      bias_init=logical(_zeros, "embed"), name="proj")(actions)
    return Mlp(self.hidden_size, self.hidden_ratio * self.hidden_size, in_axis="action",
               dtype=self.dtype, name="mlp")(actions)


class PlaceEmbedder(nn.Module):
  """Where an action points, seen from every patch: ``place [B, m, 2] -> [B, m, gh*gw, D]``.

  For actions that name a place in the image (Push-T's target position): ``place`` holds the
  normalised action numbers of its column (``x``) and row (``y``). A learned per-axis affine maps
  them to image coordinates in ``[-1, 1]`` (initialised at scale 0.5 and shift 0, right for
  standardised positions whose standard deviation is a quarter of the frame: the affine only
  has to be refined); every patch (row-major, as :class:`PatchEmbed` orders them) then sees its
  offset to that place and Gaussian bumps of the distance at ``widths`` (in the same units),
  and one linear map makes that a token embedding. A global conditioning vector would have to
  learn the image's geometry to tell a patch that the agent is going there; this says it.
  """

  hidden_size: int
  widths: tuple[float, ...] = (0.05, 0.1, 0.2, 0.4)
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, place: jax.Array, grid_h: int, grid_w: int) -> jax.Array:
    scale = self.param("scale", logical(nn.initializers.constant(0.5), None), (2,))
    shift = self.param("shift", logical(_zeros, None), (2,))
    target = place.astype(jnp.float32) * scale + shift  # [B, m, 2] as (column, row)
    rows, cols = np.meshgrid((np.arange(grid_h) + 0.5) / grid_h * 2 - 1,
                             (np.arange(grid_w) + 0.5) / grid_w * 2 - 1, indexing="ij")
    centres = np.stack([cols.reshape(-1), rows.reshape(-1)], axis=1)  # [P, 2]
    offset = centres - target[:, :, None, :]  # [B, m, P, 2]
    distance2 = jnp.sum(offset ** 2, axis=-1, keepdims=True)
    widths = np.asarray(self.widths, np.float32)
    features = jnp.concatenate([offset, jnp.exp(-distance2 / (2 * widths ** 2))], axis=-1)
    return nn.Dense(self.hidden_size, dtype=self.dtype,
                    kernel_init=logical(_xavier, None, "embed"),
                    bias_init=logical(_zeros, "embed"), name="proj")(features.astype(self.dtype))


def fourier_encode(x: jax.Array, num_frequencies: int) -> jax.Array:
  """``[..., F] -> [..., F (1 + 2K)]``: ``x``, then ``sin`` and ``cos`` of ``2^k pi x`` for
  ``k < K`` (grouped by function, then frequency, then feature)."""
  angles = (jnp.pi * 2.0 ** jnp.arange(num_frequencies, dtype=x.dtype))[:, None] * x[..., None, :]
  angles = angles.reshape(*x.shape[:-1], num_frequencies * x.shape[-1])
  return jnp.concatenate([x, jnp.sin(angles), jnp.cos(angles)], axis=-1)


class PatchEmbed(nn.Module):
  """Non-overlapping patches of each frame, linearly embedded.

  ``[B, T, H, W, C] -> [B, T, (H/p)*(W/p), D]`` (row-major patch order).
  """

  patch_size: int
  hidden_size: int
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    patches = patchify(x, self.patch_size)  # [B, T, P, p*p*C]
    return nn.Dense(self.hidden_size, dtype=self.dtype,
                    kernel_init=logical(_xavier, "patch", "embed"),
                    bias_init=logical(_zeros, "embed"), name="proj")(patches)


def patchify(x: jax.Array, p: int) -> jax.Array:
  """``[B, T, H, W, C] -> [B, T, (H/p)*(W/p), p*p*C]``, patches row-major, pixels (py, px, c)."""
  return rearrange(x, "b t (gh py) (gw px) c -> b t (gh gw) (py px c)", py=p, px=p)


def unpatchify(x: jax.Array, grid_h: int, grid_w: int, p: int) -> jax.Array:
  """Inverse of :func:`patchify`: ``[B, T, gh*gw, p*p*C] -> [B, T, gh*p, gw*p, C]``."""
  return rearrange(x, "b t (gh gw) (py px c) -> b t (gh py) (gw px) c", gh=grid_h, gw=grid_w,
                   py=p, px=p)


# --------------------------------------------------------------------------- transformer


def _float8(name: str, fp8: bool) -> Float8DotGeneral | None:
  """The float8 matmul of the layer ``name`` (its calibrated scale lives under
  ``{name}_float8``), or None: the layer's own matmul."""
  return Float8DotGeneral(name=f"{name}_float8") if fp8 else None


class Mlp(nn.Module):
  """``Linear -> GELU(tanh) -> Linear``; ``[..., in] -> [..., features]``. ``fp8``: both
  matmuls in float8 (:mod:`wmjax.nn.float8`)."""

  features: int
  hidden: int
  in_axis: str = "embed"
  dtype: Dtype = jnp.float32
  fp8: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = nn.Dense(self.hidden, dtype=self.dtype, kernel_init=logical(_xavier, self.in_axis, "mlp"),
                 bias_init=logical(_zeros, "mlp"), dot_general=_float8("fc1", self.fp8),
                 name="fc1")(x)
    x = checkpoint_name(nn.gelu(x, approximate=True), "mlp_activation")
    return nn.Dense(self.features, dtype=self.dtype, kernel_init=logical(_xavier, "mlp", "embed"),
                    bias_init=logical(_zeros, "embed"), dot_general=_float8("fc2", self.fp8),
                    name="fc2")(x)


class Attention(nn.Module):
  """Multi-head self-attention over axis 1 of ``x [N, L, ..., D]``
  (:func:`wmjax.nn.attention.attend`).

  Axes between the sequence axis and the width are batch axes, like ``N``: ``x [B, T, P, D]``
  attends across the ``T`` frames of every patch position without a transpose of the tokens to
  ``[B*P, T, D]``. Below, ``...`` stands for those axes (none for ``x [N, L, D]``).
  ``causal`` masks future positions; ``rope`` rotates queries and keys by their position:
  ``positions`` (``[L]`` or axial ``[L, k]``, see :func:`rope`), by default ``Lc .. Lc+L-1``.
  ``cache = (k, v)``, each ``[N, Lc, ..., H, d]``, holds the keys and values of ``Lc`` earlier
  positions: ``x`` is then at positions ``Lc .. Lc+L-1`` and attends to the cache as well. Returns
  the output ``[N, L, ..., D]`` and ``x``'s own keys and values (``[N, L, ..., H, d]`` each, RoPE
  applied), which a later call can take as its cache. ``fp8``: the projections in and out in
  float8 (:mod:`wmjax.nn.float8`); the attention itself keeps the compute dtype.
  """

  num_heads: int
  causal: bool = False
  rope: bool = False
  implementation: str | None = "xla"
  dtype: Dtype = jnp.float32
  fp8: bool = False

  @nn.compact
  def __call__(self, x: jax.Array, cache: tuple[jax.Array, jax.Array] | None = None,
               positions: jax.Array | None = None
               ) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    d = x.shape[-1]
    head_dim = d // self.num_heads
    # one float8 scaling of x for the three projections: XLA then quantizes x once
    qkv_dot = _float8("qkv", self.fp8)

    def project(name):
      return nn.DenseGeneral((self.num_heads, head_dim), dtype=self.dtype,
                             kernel_init=logical(_xavier, "embed", "heads", "kv"),
                             bias_init=logical(_zeros, "heads", "kv"), dot_general=qkv_dot,
                             name=name)(x)

    q, k, v = project("query"), project("key"), project("value")  # [N, L, ..., H, d]
    offset = 0 if cache is None else cache[0].shape[1]
    if self.rope:
      if positions is None:
        positions = offset + jnp.arange(x.shape[1])
      q, k = rope(q, positions), rope(k, positions)
    keys, values = (k, v) if cache is None else (
        jnp.concatenate([cache[0].astype(k.dtype), k], axis=1),
        jnp.concatenate([cache[1].astype(v.dtype), v], axis=1))
    out = checkpoint_name(attend(q, keys, values, causal=self.causal, backend=self.implementation),
                          "attention")
    out = nn.DenseGeneral(d, axis=(-2, -1), dtype=self.dtype,
                          kernel_init=logical(_xavier, "heads", "kv", "embed"),
                          bias_init=logical(_zeros, "embed"),
                          dot_general=_float8("out", self.fp8), name="out")(out)
    return out, (k, v)


def layer_norm(x: jax.Array) -> jax.Array:
  """LayerNorm without affine parameters (eps 1e-6), computed in float32."""
  x32 = x.astype(jnp.float32)
  mean = x32.mean(-1, keepdims=True)
  var = jnp.square(x32 - mean).mean(-1, keepdims=True)
  return ((x32 - mean) * jax.lax.rsqrt(var + 1e-6)).astype(x.dtype)


def modulate(x: jax.Array, shift: jax.Array, scale: jax.Array) -> jax.Array:
  return x * (1 + scale) + shift


class Modulation(nn.Module):
  """adaLN-Zero regression ``SiLU -> Linear(D, n*D)``, zero-initialised; ``[..., D] -> n x [..., D]``."""

  num_chunks: int
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, cond: jax.Array) -> tuple[jax.Array, ...]:
    d = cond.shape[-1]
    out = nn.Dense(self.num_chunks * d, dtype=self.dtype,
                   kernel_init=logical(_zeros, "embed", "modulation"),
                   bias_init=logical(_zeros, "modulation"), name="proj")(nn.silu(cond))
    return tuple(jnp.split(out, self.num_chunks, axis=-1))


class STBlock(nn.Module):
  """DiT adaLN-Zero block attending over one axis of the ``[B, T, P, D]`` token grid.

  ``axis='spatial'``: the P patches of each frame attend to each other.
  ``axis='temporal'``: each patch position attends across the T frames (optionally causal), and
  across the ``Tc`` earlier frames of ``cache`` (keys, values ``[B*P, Tc, H, d]``) when given; the
  patches are a batch axis of that attention, so the tokens keep their ``[B, T, P, D]`` layout.
  ``cond [B, T, D]`` is the per-frame conditioning vector; it modulates every token of its frame.
  With ``rope``, ``positions`` are the RoPE positions of the attended axis (for the spatial axis
  the ``[P, 2]`` (row, column) of each patch: relative 2-D positions; for the temporal axis the
  frame index by default). Returns ``x' [B, T, P, D]`` and, for the temporal axis, the keys and values of ``x``'s frames
  (``[B*P, T, H, d]`` each; None for the spatial axis). ``fp8``: the attention's projections and
  the MLP in float8 (:mod:`wmjax.nn.float8`); the adaLN modulation keeps the compute dtype.
  """

  axis: str
  num_heads: int
  mlp_ratio: int = 4
  causal: bool = False
  rope: bool = False
  attention_impl: str | None = "xla"
  dtype: Dtype = jnp.float32
  fp8: bool = False

  @nn.compact
  def __call__(self, x: jax.Array, cond: jax.Array, cache=None, positions=None):
    x = constrain(x)
    b, t, p, d = x.shape
    shift_a, scale_a, gate_a, shift_m, scale_m, gate_m = (
        m[:, :, None, :] for m in Modulation(6, dtype=self.dtype, name="modulation")(cond))
    attention = Attention(self.num_heads, causal=self.causal, rope=self.rope,
                          implementation=self.attention_impl, dtype=self.dtype, fp8=self.fp8,
                          name="attn")
    h = checkpoint_name(modulate(layer_norm(x), shift_a, scale_a), "normed")
    if self.axis == "spatial":
      if cache is not None:
        raise ValueError("spatial attention takes no cache: frames attend within themselves")
      # each frame's patches attend to each other: sequences of P tokens
      h = attention(rearrange(h, "b t p d -> (b t) p d"), positions=positions)[0]
      h, kv = rearrange(h, "(b t) p d -> b t p d", b=b), None
    elif self.axis == "temporal":
      # each patch position attends across frames: sequences of T tokens, P a batch axis
      if cache is not None:
        cache = tuple(rearrange(a, "(b p) t h k -> b t p h k", b=b) for a in cache)
      h, kv = attention(h, cache)
      kv = tuple(rearrange(a, "b t p h k -> (b p) t h k") for a in kv)
    else:
      raise ValueError(f"axis must be 'spatial' or 'temporal', got {self.axis!r}")
    x = x + gate_a * h
    h = checkpoint_name(modulate(layer_norm(x), shift_m, scale_m), "normed")
    h = Mlp(d, self.mlp_ratio * d, dtype=self.dtype, fp8=self.fp8, name="mlp")(h)
    return constrain(x + gate_m * h), kv


class STLayer(nn.Module):
  """One spatial block and one temporal block (the unit that is stacked / scanned): spatial
  first (IRASim), or temporal first, which lets every spatial block of the stack see the earlier
  frames (the first spatial block of a spatial-first stack sees only its own noisy frame).

  ``x [B, T, P, D]``, ``spatial_cond`` and ``temporal_cond`` ``[B, T, D]``, the ``[P, 2]`` (row,
  column) of every patch (used by the spatial block's RoPE when ``spatial_rope``), optional
  temporal ``cache`` (see :class:`STBlock`), optional ``frame_pos [1, T, 1, D]`` added to the
  tokens right before the temporal block -> ``(x', kv)`` with ``x' [B, T, P, D]`` and ``kv`` the
  temporal keys and values of ``x``'s frames when ``return_kv`` (else None); the ``(carry,
  output)`` pair is what ``nn.scan`` expects. ``fp8``: see :class:`STBlock`.
  """

  num_heads: int
  mlp_ratio: int = 4
  causal: bool = False
  rope: bool = False
  attention_impl: str | None = "xla"
  dtype: Dtype = jnp.float32
  fp8: bool = False
  return_kv: bool = False
  temporal_first: bool = False
  spatial_rope: bool = False

  @nn.compact
  def __call__(self, x, spatial_cond, temporal_cond, patch_positions, cache=None, frame_pos=None):
    common = dict(num_heads=self.num_heads, mlp_ratio=self.mlp_ratio,
                  attention_impl=self.attention_impl, dtype=self.dtype, fp8=self.fp8)
    spatial = STBlock("spatial", rope=self.spatial_rope, **common, name="spatial")
    temporal_block = STBlock("temporal", causal=self.causal, rope=self.rope, **common,
                             name="temporal")

    def temporal(x):
      return temporal_block(x if frame_pos is None else x + frame_pos, temporal_cond, cache)

    if self.temporal_first:
      x, kv = temporal(x)
      x, _ = spatial(x, spatial_cond, positions=patch_positions)
    else:
      x, _ = spatial(x, spatial_cond, positions=patch_positions)
      x, kv = temporal(x)
    return x, kv if self.return_kv else None


class FinalLayer(nn.Module):
  """adaLN (shift, scale) then a zero-initialised linear map to patch pixels.

  ``x [B, T, P, D]``, ``cond [B, T, D]`` -> ``[B, T, P, p*p*C]``.
  """

  out_features: int
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, cond: jax.Array) -> jax.Array:
    shift, scale = (m[:, :, None, :] for m in Modulation(2, dtype=self.dtype,
                                                          name="modulation")(cond))
    x = modulate(layer_norm(x), shift, scale)
    return nn.Dense(self.out_features, dtype=self.dtype,
                    kernel_init=logical(_zeros, "embed", "patch"),
                    bias_init=logical(_zeros, "patch"), name="linear")(x)
