"""Forward time, achieved FLOP/s, rollout frames/s and peak memory of any world-model config;
writes JSON.

  python benchmarks/forward_rollout.py --config configs/irasim.py:S --batch 1 --batch 8 \
      --frames 30 [--config.model.dtype=bfloat16 ...] [--out benchmarks/results/NAME.json]

Forward: one network call on a full window ``[B, c+h, H, W, C]`` (``config.frame_shape``).
Rollout: ``--frames`` new frames from ``c`` context frames with the config's sampler, context and
horizon (``sampling.num_steps=59`` costs what IRASim's PNDM-50 does: 59 network calls per block;
``sampling.kv_cache`` is recorded; a ``model.fp8_matmuls`` network runs with static float8
scales, calibrated on random windows); frames/s counts generated frames over all B rollouts. Times
are medians over ``--repeats`` runs after one compile run. ``--batch`` may be given several times:
batches run in increasing order (so the allocator's peak after each is that batch's peak) and the
result names the batch with the most frames/s. ``--profile DIR`` traces one more rollout of each
batch and adds its device time by op to the JSON (benchmarks/profile_ops.py).
"""

from __future__ import annotations

import argparse
import platform

import jax
import jax.numpy as jnp

from common import (add_config_arguments, median_seconds, parse_args, peak_memory,
                    write_result)
from profile_ops import format_table, top_ops
from wmjax.config import load_config
from wmjax.model import WorldModel
from wmjax.nn import forward_flops
from wmjax.rollout import block_flops, rollout


def benchmark(config_spec: str, overrides: list[str], batch: int, frames: int,
              repeats: int, profile_dir: str | None = None) -> dict:
  config = load_config(config_spec, overrides)
  wm = WorldModel.from_config(config)
  net = wm.network
  c, h = config.rollout.context, config.rollout.horizon
  shape = tuple(config.frame_shape)
  params = wm.init(jax.random.key(0), shape, frames=c + h)
  n = c + h
  x = jax.random.normal(jax.random.key(1), (batch, n) + shape)
  t = jnp.full((batch, n), 500.0)
  actions = jnp.zeros((batch, n - 1, net.action_dim))
  if net.fp8_matmuls:  # static float8 scales, as a calibrated model runs (on noise: speed only)
    params = wm.calibrate_float8(params, x, actions, jax.random.key(4), context=c)
  forward = jax.jit(net.apply)
  forward_s, forward_compile_s = median_seconds(lambda: forward(params, x, t, actions), repeats)
  flops = forward_flops(net, batch, n, shape[0], shape[1])

  context = jax.random.normal(jax.random.key(2), (batch, c) + shape)
  rollout_actions = jnp.zeros((batch, frames, net.action_dim))
  run = lambda: rollout(wm, params, context, rollout_actions, jax.random.key(3), horizon=h)
  rollout_s, rollout_compile_s = median_seconds(run, repeats)
  profile = None
  if profile_dir:
    profile = top_ops(run, 1, f"{profile_dir}/b{batch}")
    print(format_table(profile), flush=True)
  calls = wm.sampler.model_calls(h) * (2 if wm.guided else 1)
  blocks = -(-frames // h)
  flops_per_block = block_flops(wm, batch, c, h, shape[0], shape[1])
  return {
      "config": config_spec, "overrides": overrides, "name": config.name or config_spec,
      "device": jax.devices()[0].device_kind, "platform": jax.default_backend(),
      "num_devices": jax.device_count(), "host": platform.node(), "jax": jax.__version__,
      "dtype": net.dtype, "batch": batch, "frame_shape": shape, "window_frames": n,
      "forward_ms": forward_s * 1e3, "forward_compile_s": forward_compile_s,
      "forward_gflop": flops / 1e9, "forward_tflops_per_s": flops / forward_s / 1e12,
      "rollout_frames": frames, "context": c, "horizon": h, "sampler": wm.sampler.sampler,
      "sampling_steps": wm.sampler.num_steps, "model_calls_per_block": calls,
      "rollout_s": rollout_s, "rollout_compile_s": rollout_compile_s,
      "rollout_frames_per_s": batch * frames / rollout_s,
      "rollout_tflops_per_s": blocks * flops_per_block / rollout_s / 1e12,
      "kv_cache": wm.sampler.kv_cache, "attention_impl": net.attention_impl,
      **peak_memory(),
      "profile": profile,
  }


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  add_config_arguments(parser)
  parser.add_argument("--batch", type=int, action="append",
                      help="rollouts per batch (repeatable; default 1)")
  parser.add_argument("--frames", type=int, default=15, help="frames to generate per rollout")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--profile", default=None, metavar="DIR",
                      help="trace one more rollout per batch into DIR; device time by op")
  args = parse_args(parser)
  batches = sorted(set(args.batch or [1]))
  runs = [benchmark(args.config, args.overrides, b, args.frames, args.repeats, args.profile)
          for b in batches]
  best = max(runs, key=lambda r: r["rollout_frames_per_s"])
  result = dict(best, batches=runs) if len(runs) > 1 else best
  args.batch = best["batch"]
  write_result("forward_rollout", result, args)


if __name__ == "__main__":
  main()
