"""Multi-head dot-product attention with a backend chosen by config.

``attend(q, k, v)`` takes ``q [N, Lq, H, d]`` and ``k, v [N, Lk, H, d]`` and returns
``[N, Lq, H, d]``. Queries are the last ``Lq`` positions of the ``Lk`` keys (``Lq <= Lk``): with
``causal=True`` query ``i`` sees keys ``0 .. Lk - Lq + i``, which is ordinary causal attention when
``Lq == Lk`` and attention after a cached prefix (the temporal KV cache) when ``Lq < Lk``.
More batch axes may sit between the sequence and the heads: ``q [N, Lq, M, H, d]`` for temporal
attention over ``[B, T, P, H, d]`` tokens, the patches a batch axis, computes in that layout
under XLA (the flash kernels fold ``M`` into ``N``, a transpose).

Backends (``model.attention_impl``):

``xla``     ``jax.nn.dot_product_attention(implementation='xla')``; every platform, every dtype.
``cudnn``   cuDNN flash attention (``implementation='cudnn'``); GPU only, bf16 / fp16 inputs.
            Head dimensions are zero-padded to a multiple of 8 (cuDNN's requirement) and the
            softmax scale is kept at ``1/sqrt(d)`` of the true head dimension. Sequences of
            fewer than ``FLASH_MIN_KEYS`` keys (the temporal axis) go through XLA: the flash
            kernel's 64 x 128 tiles would be mostly padding (on an H100, IRASim-XL/2's train
            step spent 143 ms of 724 in cuDNN attention with the 16-frame temporal attention in
            it; benchmarks/RESULTS.md).
``splash``  Pallas splash attention, the TPU flash kernel. Sequences are padded to whole
            128-token blocks and the padding is masked with segment ids. Sequences shorter than
            one block (the temporal axis: a few frames) go through XLA, which is faster for them.
            Off TPU the kernel runs in Pallas interpret mode: exact but slow, for tests.
``auto``    ``cudnn`` on GPU for bf16 / fp16, ``splash`` on TPU, ``xla`` otherwise.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from wmjax.parallel import BATCH_AXES

ATTENTION_BACKENDS = ("xla", "cudnn", "splash", "auto")
FLASH_DTYPES = (jnp.bfloat16, jnp.float16)
SPLASH_BLOCK = 128  # token block of the splash kernel (the TPU lane width)
FLASH_MIN_KEYS = 64  # shorter attention goes through XLA under the cudnn backend


_PLATFORM = contextvars.ContextVar("wmjax_attention_platform", default=None)


@contextlib.contextmanager
def platform_override(platform: str):
  """Resolve backends for ``platform`` ('gpu', 'tpu', 'cpu') instead of JAX's default backend:
  for compiling a model for devices this process does not run on (``wmjax compile``)."""
  token = _PLATFORM.set(platform)
  try:
    yield
  finally:
    _PLATFORM.reset(token)


def current_platform() -> str:
  """The platform attention is built for: the override, else JAX's default backend."""
  return _PLATFORM.get() or jax.default_backend()


def check_backend(name: str | None, dtype) -> None:
  """ValueError for a backend that does not exist or cannot take ``dtype`` (the compute dtype)."""
  if name is not None and name not in ATTENTION_BACKENDS:
    raise ValueError(f"attention_impl must be one of {ATTENTION_BACKENDS}, got {name!r}")
  if name == "cudnn" and jnp.dtype(dtype) not in FLASH_DTYPES:
    raise ValueError(f"attention_impl='cudnn' (cuDNN flash attention) computes in bfloat16 or "
                     f"float16; set model.dtype='bfloat16', got {jnp.dtype(dtype).name}")


def resolve_backend(name: str | None, dtype, platform: str | None = None) -> str:
  """The backend that runs: ``auto`` and None resolved for ``platform`` (default: JAX's)."""
  check_backend(name, dtype)
  platform = platform or current_platform()
  if name is None:
    return "xla"
  if name == "auto":
    if platform == "gpu" and jnp.dtype(dtype) in FLASH_DTYPES:
      return "cudnn"
    return "splash" if platform == "tpu" else "xla"
  if name == "cudnn" and platform != "gpu":
    raise ValueError(f"attention_impl='cudnn' needs a GPU, but JAX runs on {platform!r}; "
                     f"use 'xla' or 'auto'")
  return name


def prefix_causal_mask(query_len: int, key_len: int) -> np.ndarray:
  """``[Lq, Lk]`` bool: query ``i`` (position ``Lk - Lq + i``) sees keys up to its own position."""
  offset = key_len - query_len
  return np.arange(key_len)[None, :] <= offset + np.arange(query_len)[:, None]


def _check_shapes(q, k, v) -> None:
  if (q.ndim < 4 or k.shape != v.shape or k.ndim != q.ndim
      or q.shape[:1] + q.shape[2:] != k.shape[:1] + k.shape[2:]):
    raise ValueError(f"attention needs q [N, Lq, ..., H, d] and k, v [N, Lk, ..., H, d] with "
                     f"matching N, ..., H, d; got q {q.shape}, k {k.shape}, v {v.shape}")
  if q.shape[1] > k.shape[1]:
    raise ValueError(f"attention needs at least as many keys as queries, got Lq={q.shape[1]} > "
                     f"Lk={k.shape[1]}")


def attend(q: jax.Array, k: jax.Array, v: jax.Array, *, causal: bool = False,
           backend: str | None = "xla") -> jax.Array:
  """Softmax attention ``[N, Lq, ..., H, d] x [N, Lk, ..., H, d]^2 -> [N, Lq, ..., H, d]`` (see
  module doc)."""
  _check_shapes(q, k, v)
  name = resolve_backend(backend, q.dtype)
  flash = ((name == "cudnn" and k.shape[1] >= FLASH_MIN_KEYS)
           or (name == "splash" and q.shape[1] >= SPLASH_BLOCK))
  if flash and q.ndim > 4:
    # the flash kernels take one batch axis: the others join N, a transpose of q, k, v and out
    fold = lambda a: jnp.moveaxis(a, 1, -3).reshape((-1,) + a.shape[1:2] + a.shape[-2:])
    out = attend(fold(q), fold(k), fold(v), causal=causal, backend=name)
    return jnp.moveaxis(out.reshape(q.shape[:1] + q.shape[2:-2] + out.shape[1:]), -3, 1)
  if name == "cudnn" and flash:
    return _cudnn(q, k, v, causal)
  if flash:
    return _splash(q, k, v, causal)
  return _xla(q, k, v, causal) if q.ndim == 4 else _xla_batched(q, k, v, causal)


def _mask(q, k, causal: bool):
  """(is_causal, mask) for ``jax.nn.dot_product_attention``: its own causal mask when aligned."""
  if not causal or q.shape[1] == k.shape[1]:
    return causal, None
  return False, jnp.asarray(prefix_causal_mask(q.shape[1], k.shape[1]))


def _xla(q, k, v, causal):
  is_causal, mask = _mask(q, k, causal)
  return jax.nn.dot_product_attention(q, k, v, mask=mask, is_causal=is_causal,
                                      implementation="xla")


def _xla_batched(q, k, v, causal):
  """``jax.nn.dot_product_attention(implementation='xla')``'s arithmetic (float32 logits and
  softmax, ``1/sqrt(d)`` scale) for ``q [N, Lq, ..., H, d]``: the einsums take the axes between
  the sequence and the heads as batch axes where they are, so the caller transposes nothing."""
  batch = "abcdefgijklm"[:q.ndim - 4]
  precision = {jnp.dtype(jnp.bfloat16): jax.lax.DotAlgorithmPreset.BF16_BF16_F32,
               jnp.dtype(jnp.float16): jax.lax.DotAlgorithmPreset.F16_F16_F32}.get(q.dtype)
  logits = jnp.einsum(f"nq{batch}hd,ns{batch}hd->n{batch}hqs", q, k, precision=precision,
                      preferred_element_type=jnp.promote_types(q.dtype, jnp.float32))
  logits = logits * jnp.asarray(1.0 / math.sqrt(q.shape[-1]), logits.dtype)
  if causal:
    mask = jnp.asarray(prefix_causal_mask(q.shape[1], k.shape[1]))
    logits = jnp.where(mask, logits, jnp.asarray(-0.7 * jnp.finfo(logits.dtype).max,
                                                 logits.dtype))
  probs = jax.nn.softmax(logits.astype(jnp.float32), axis=-1).astype(v.dtype)
  return jnp.einsum(f"n{batch}hqs,ns{batch}hd->nq{batch}hd", probs, v)


def _cudnn(q, k, v, causal):
  d = q.shape[-1]
  pad = -d % 8
  if pad:
    widths = ((0, 0),) * 3 + ((0, pad),)
    q, k, v = (jnp.pad(a, widths) for a in (q, k, v))  # zero dims change neither logits nor outputs
  is_causal, mask = _mask(q, k, causal)
  out = jax.nn.dot_product_attention(q, k, v, mask=mask, is_causal=is_causal,
                                     scale=1.0 / math.sqrt(d), implementation="cudnn")
  return out[..., :d]


def _splash_kernel(heads: int, query_len: int, key_len: int, causal_offset: int | None,
                   interpret: bool):
  """A splash kernel for ``[H, L, d]`` inputs; ``causal_offset`` None: no causal mask."""
  from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_kernel as kernel
  from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_mask as masks
  shape = (query_len, key_len)
  if causal_offset is None:
    head_mask = masks.FullMask(shape)
  else:
    head_mask = masks.CausalMask(shape, offset=causal_offset)
  block_q = max(b for b in (512, 256, 128) if query_len % b == 0)
  block_kv = max(b for b in (512, 256, 128) if key_len % b == 0)
  sizes = kernel.BlockSizes(block_q=block_q, block_kv=block_kv, block_kv_compute=block_kv,
                            block_q_dkv=block_q, block_kv_dkv=block_kv,
                            block_kv_dkv_compute=block_kv, block_q_dq=block_q, block_kv_dq=block_kv)
  return kernel.make_splash_mha(masks.MultiHeadMask([head_mask] * heads), block_sizes=sizes,
                                head_shards=1, q_seq_shards=1, interpret=interpret)


def _splash(q, k, v, causal):
  """Splash attention; under a mesh context (``jax.set_mesh``, as the trainer and sharded
  rollouts set) one kernel per device through ``shard_map``: XLA cannot partition a Pallas call.
  The sequences' leading axis (batch-major) is split over the batch axes, heads over ``tensor``."""
  batch, heads = split_axes(q.shape[0], q.shape[2])
  if batch is None and heads is None:
    return _splash_local(q, k, v, causal)
  spec = PartitionSpec(batch, None, heads, None)
  local = functools.partial(_splash_local, causal=causal)
  return jax.shard_map(local, mesh=jax.sharding.get_abstract_mesh(), in_specs=(spec, spec, spec),
                       out_specs=spec, check_vma=False)(q, k, v)


def split_axes(leading: int, split: int | None = None):
  """How a Pallas call (which XLA cannot partition) is split under the current mesh (``jax.set_mesh``,
  as the trainer and sharded rollouts set): the mesh's batch axes (:data:`BATCH_AXES` of size > 1)
  that evenly split a ``leading`` (batch-major) axis, or None; ``'tensor'`` when it has size > 1
  and evenly splits ``split`` (heads, hidden width), else None. Both None off a mesh."""
  mesh = jax.sharding.get_abstract_mesh()
  names = mesh.axis_names if not mesh.empty else ()
  batch = tuple(a for a in BATCH_AXES if a in names and mesh.shape[a] > 1)
  if batch and leading % math.prod(mesh.shape[a] for a in batch):
    batch = ()
  tensor = "tensor" if (split is not None and "tensor" in names and mesh.shape["tensor"] > 1
                        and split % mesh.shape["tensor"] == 0) else None
  return batch or None, tensor


def _splash_local(q, k, v, causal):
  from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_kernel as kernel
  n, lq, h, d = q.shape
  lk = k.shape[1]
  pad_q, pad_k = -lq % SPLASH_BLOCK, -lk % SPLASH_BLOCK
  # Padding goes at the end of queries and keys and forms a second segment: real queries never
  # see padded keys, and every padded query sees at least the first padded key.
  end_pad = lambda a, pad: jnp.pad(a, ((0, 0), (0, pad), (0, 0), (0, 0)))
  q = end_pad(q * jnp.asarray(1.0 / math.sqrt(d), q.dtype), pad_q)
  k, v = end_pad(k, pad_k), end_pad(v, pad_k)
  segments = kernel.SegmentIds(q=jnp.asarray(np.arange(lq + pad_q) >= lq, jnp.int32),
                               kv=jnp.asarray(np.arange(lk + pad_k) >= lk, jnp.int32))
  run = _splash_kernel(h, lq + pad_q, lk + pad_k, lk - lq if causal else None,
                       current_platform() != "tpu")
  heads_first = lambda a: a.transpose(0, 2, 1, 3)  # the kernel's layout [H, L, d]
  out = jax.vmap(run, in_axes=(0, 0, 0, None))(heads_first(q), heads_first(k), heads_first(v),
                                               segments)
  return heads_first(out)[:, :lq]
