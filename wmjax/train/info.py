"""What a config costs, without allocating its model: parameters, FLOPs, sampling cost and a
per-device training-memory estimate (``wmjax info``)."""

from __future__ import annotations

import jax
import ml_collections
import numpy as np

from wmjax.model import WorldModel
from wmjax.nn import forward_flops
from wmjax.rollout import block_flops


def config_info(config: ml_collections.ConfigDict, devices: int | None = None,
                name: str | None = None) -> dict:
  """Parameter count (from abstract shapes), forward GFLOP of one window, model calls and GFLOP
  per generated frame of a rollout block and, for a training config, the analytic memory per
  device over ``devices`` (default: this machine's)."""
  wm = WorldModel.from_config(config)
  h, w, c = config.frame_shape
  frames = config.rollout.context + config.rollout.horizon
  shapes = jax.eval_shape(lambda: wm.init(jax.random.key(0), (h, w, c), frames=frames))
  params = sum(int(np.prod(p.shape)) for p in jax.tree.leaves(shapes))
  guidance = 2 if wm.guided else 1
  sampling = block_flops(wm, 1, config.rollout.context, config.rollout.horizon, h, w)
  info = {
      "name": config.name or name,
      "parameters": params,
      "parameter_bytes_fp32": 4 * params,
      "frame_shape": [h, w, c],
      "window_frames": frames,
      "forward_gflop_per_window": forward_flops(wm.network, 1, frames, h, w) / 1e9,
      "model_calls_per_block": wm.sampler.model_calls(config.rollout.horizon) * guidance,
      "kv_cache": wm.sampler.kv_cache,
      "gflop_per_generated_frame": sampling / config.rollout.horizon / 1e9,
  }
  if "batch_size" in config and "mesh" in config:
    from wmjax.train import memory
    info["train_memory_per_device"] = memory.estimate(config, wm, devices)
  return info
