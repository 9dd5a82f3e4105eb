"""Train-step time, samples/s and model FLOP utilisation (MFU) of any config; writes JSON.

  python benchmarks/train_step.py --config configs/irasim.py:XL --batch 8 \
      --config.model.dtype=bfloat16 [--config.model.remat=dots] [--peak_tflops 989]

``--profile DIR`` traces three more steps with ``jax.profiler`` and adds the device time per op
class and the top ops to the JSON (benchmarks/profile_ops.py).

MFU = analytic model FLOPs of a train step (3 x forward: forward + backward, remat recomputation
not counted) / step time / peak FLOP/s. The peak defaults to the dense bf16 figure of known
accelerators (H100 / H200: 989 TFLOP/s, A100: 312); on CPU pass --peak_tflops or MFU is omitted.
Synthetic batches on a ('data', 'fsdp', 'tensor') mesh of all devices (--mesh, default -1,1,1).
"""

from __future__ import annotations

import argparse
import gzip
import statistics
import time

import jax
import jax.numpy as jnp

from common import (add_config_arguments, add_kernel_arguments, kernel_overrides,
                    check_fits, compiled_memory, parse_args, peak_memory, write_result)
from profile_ops import format_table, top_ops
from wmjax.config import load_config
from wmjax.model import WorldModel
from wmjax.nn import forward_flops
from wmjax.parallel import make_mesh
from wmjax.train.step import ShardedTrainer

PEAK_BF16_TFLOPS = {"H100": 989.0, "H200": 989.0, "A100": 312.0}


def peak_tflops(device_kind: str) -> float | None:
  for name, peak in PEAK_BF16_TFLOPS.items():
    if name in device_kind:
      return peak
  return None


def benchmark(spec: str, overrides: list[str], batch: int, frames: int | None, steps: int,
              mesh_shape: tuple[int, int, int], peak: float | None,
              profile_dir: str | None = None, hlo_path: str | None = None) -> dict:
  config = load_config(spec, overrides)
  wm = WorldModel.from_config(config)
  frames = frames or wm.network.num_frames
  shape = tuple(config.frame_shape)
  trainer = ShardedTrainer(wm, config, make_mesh(mesh_shape), shape, frames)
  state = trainer.init(jax.random.key(0))
  x = jax.device_put(jax.random.normal(jax.random.key(1), (batch, frames) + shape),
                     trainer.batch_sharding)
  actions = jax.device_put(jnp.zeros((batch, frames - 1, wm.network.action_dim)),
                           trainer.batch_sharding)
  start = time.perf_counter()
  compiled = trainer.compile(state, x, actions)
  compile_s = time.perf_counter() - start
  memory = compiled_memory(compiled)
  check_fits(memory)
  if hlo_path:
    with gzip.open(hlo_path, "wt") as f:
      f.write(compiled.as_text())
  print(f"compiled in {compile_s:.0f} s: {memory}", flush=True)
  state, metrics = trainer.step(state, x, actions)
  jax.block_until_ready(metrics)
  times = []
  for _ in range(steps):
    start = time.perf_counter()
    state, metrics = trainer.step(state, x, actions)
    jax.block_until_ready(metrics)
    times.append(time.perf_counter() - start)
  step_s = statistics.median(times)
  profile = None
  if profile_dir:
    def one_step():
      nonlocal state, metrics
      state, metrics = trainer.step(state, x, actions)
      return metrics
    profile = top_ops(one_step, 3, profile_dir)
    print(format_table(profile), flush=True)
  flops = 3 * forward_flops(wm.network, batch, frames, shape[0], shape[1])
  device = jax.devices()[0].device_kind
  peak = peak or peak_tflops(device)
  achieved = flops / step_s / 1e12
  return {
      "config": spec, "overrides": overrides, "name": config.name or spec, "device": device,
      "num_devices": jax.device_count(), "mesh": list(trainer.mesh.shape.values()),
      "jax": jax.__version__, "dtype": wm.network.dtype, "remat": wm.network.remat,
      "batch": batch, "frames": frames, "frame_shape": shape, "compile_s": compile_s,
      "step_ms": step_s * 1e3, "samples_per_s": batch / step_s,
      "train_tflop_per_step": flops / 1e12, "achieved_tflops_per_s": achieved,
      "peak_tflops_per_s": peak, "mfu": achieved / (peak * jax.device_count()) if peak else None,
      "mlp_kernel": wm.network.mlp_kernel, "norm_kernel": wm.network.norm_kernel,
      "loss": float(metrics["loss"]), "compiled_memory": memory, **peak_memory(),
      "profile": profile,
  }


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  add_config_arguments(parser)
  parser.add_argument("--batch", type=int, default=8, help="global batch")
  parser.add_argument("--frames", type=int, default=None, help="default: model.num_frames")
  parser.add_argument("--steps", type=int, default=5)
  parser.add_argument("--mesh", default="-1,1,1", help="data,fsdp,tensor")
  parser.add_argument("--peak_tflops", type=float, default=None, help="per-device peak")
  parser.add_argument("--profile", default=None, metavar="DIR",
                      help="trace 3 steps into DIR and report device time by op")
  add_kernel_arguments(parser)
  parser.add_argument("--hlo", default=None, metavar="FILE.gz",
                      help="write the compiled step's HLO text (gzipped), to look up profiled ops")
  args = parse_args(parser)
  kernel, mlp_blocks = kernel_overrides(args)
  mesh = tuple(int(v) for v in args.mesh.split(","))
  result = benchmark(args.config, args.overrides + kernel, args.batch, args.frames, args.steps,
                     mesh, args.peak_tflops, args.profile, args.hlo)
  result["mlp_blocks"] = mlp_blocks
  write_result("train_step", result, args)


if __name__ == "__main__":
  main()
