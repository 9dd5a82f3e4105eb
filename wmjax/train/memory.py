"""A per-device memory estimate of a training config, printed before anything compiles.

State: float32 parameters, EMA and AdamW's two moments (16 bytes a parameter) plus float32
gradients (4), sharded over the ``fsdp`` x ``tensor`` mesh axes. Activations kept for the
backward pass, per layer (one spatial + one temporal block) and per token of the local batch
(``D`` = hidden size, ``b`` = bytes of the compute dtype, ``h`` = heads, ``S`` = attention length):

  remat 'none'              ~ (16 D + 2 (4 D) ) b  + h S b for each block's softmax  (everything)
  remat 'dots_elementwise'  ~ (3 D + D + 4 D + D + D + 2 D + 4 D) b   (+ attention outputs, the
                                                        normed inputs and the GELU output)
  remat 'dots_all'          ~ (3 D + D + 4 D + D) b + h S b           (matmul outputs)
  remat 'dots_attention'    ~ (3 D + D + 4 D + D + D) b               (+ attention outputs)
  remat 'dots'              ~ (3 D + D + 4 D + D) b                   (weight matmuls)
  remat 'full'              ~ D b                                     (layer inputs)

plus one layer's full activations for the recomputation. These are estimates: XLA fuses,
reuses and adds workspace buffers. On IRASim-S (2 layers, batch 2 x 16 frames of 32x40x4, fp32,
CPU) the estimate / XLA's compiled temp memory were 1.6 / 3.4 GiB without remat, 1.3 / 1.6 GiB
with 'dots' and 0.8 / 1.3 GiB with 'full': read it as the order of magnitude and as how remat,
dtype, batch and sharding move it.
"""

from __future__ import annotations

import jax
import ml_collections
import numpy as np

from wmjax.train.self_forcing import model_frames

GIB = 1024 ** 3


def _per_token_bytes(hidden: int, dtype_bytes: int, remat: str, heads: int,
                     spatial_len: int, temporal_len: int) -> float:
  attention = heads * (spatial_len + temporal_len) * dtype_bytes  # both blocks' softmax
  full = 2 * (16 * hidden + 8 * hidden) * dtype_bytes + attention
  kept = {"none": full, "dots_elementwise": 2 * 16 * hidden * dtype_bytes,
          "dots_all": 2 * 9 * hidden * dtype_bytes + attention,
          "dots_attention": 2 * 10 * hidden * dtype_bytes,
          "dots": 2 * 9 * hidden * dtype_bytes, "full": hidden * dtype_bytes}
  return kept[remat]


def estimate(config: ml_collections.ConfigDict, world_model, num_devices: int | None = None
             ) -> dict:
  """Bytes per device of the train state, gradients and activations of ``config``, whose world
  model (:class:`wmjax.model.WorldModel`) is ``world_model``, on ``num_devices`` (default: all
  of this job's)."""
  net = world_model.network
  frames = model_frames(config) if "data" in config else net.num_frames
  shapes = jax.eval_shape(lambda: world_model.init(jax.random.key(0), tuple(config.frame_shape),
                                                   frames))
  params = sum(int(np.prod(p.shape)) for p in jax.tree.leaves(shapes))
  devices = num_devices or jax.device_count()
  mesh = list(config.mesh)
  if -1 in mesh:
    mesh[mesh.index(-1)] = devices // int(np.prod([d for d in mesh if d != -1]))
  data_parallel, model_parallel = mesh[0] * mesh[1], mesh[1] * mesh[2]
  h, w = config.frame_shape[0] // net.patch_size, config.frame_shape[1] // net.patch_size
  local_batch = max(1, config.batch_size // data_parallel)
  tokens = local_batch * frames * h * w
  dtype_bytes = np.dtype(net.dtype).itemsize
  per_token = _per_token_bytes(net.hidden_size, dtype_bytes, net.remat, net.num_heads, h * w,
                               frames)
  layers = net.depth // 2
  one_layer = _per_token_bytes(net.hidden_size, dtype_bytes, "none", net.num_heads, h * w, frames)
  activations = tokens * (layers * per_token + (one_layer if net.remat != "none" else 0))
  activations /= mesh[2]  # tensor parallelism splits heads and MLP
  state = 16 * params / model_parallel
  gradients = 4 * params / model_parallel
  return {"parameters": params, "devices": devices, "mesh": mesh,
          "local_batch": local_batch, "remat": net.remat, "dtype": str(net.dtype),
          "state_gib": state / GIB, "gradients_gib": gradients / GIB,
          "activations_gib": activations / GIB,
          "total_gib": (state + gradients + activations) / GIB}

