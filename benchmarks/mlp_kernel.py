"""The fused MLP kernels (wmjax.nn.kernels.mlp) against XLA, forward + backward, on one device.

  python benchmarks/mlp_kernel.py --rows 81920 --width 1152 \
      --blocks 128,128,64,8,3 --blocks 128,128,64,4,4 --out benchmarks/results/h100/mlp.json

Times ``value_and_grad`` of ``sum(MLP(x) * probe)`` (the train step's MLP work: 6 matmuls of
``2 rows width 4 width`` FLOPs each plus the GELU and bias passes) for XLA (``nn.Dense`` ops) and
for the Pallas kernels at each ``--blocks`` setting (rows,cols,depth,warps,stages), in bf16, and
checks each against a float32 XLA reference on the same inputs (largest error of the output and
of each gradient, relative to the reference's largest magnitude). On a GPU only: elsewhere the
kernels run in interpret mode, which says nothing about speed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import jax
import jax.numpy as jnp

from common import median_seconds
from wmjax.nn.kernels import mlp as fused


def _inputs(rows: int, width: int, ratio: int, dtype):
  keys = jax.random.split(jax.random.key(0), 6)
  hidden = ratio * width
  return (jax.random.normal(keys[0], (rows, width), dtype),
          (jax.random.normal(keys[1], (width, hidden)) / width ** 0.5).astype(dtype),
          (jax.random.normal(keys[2], (hidden,)) * 0.1).astype(dtype),
          (jax.random.normal(keys[3], (hidden, width)) / hidden ** 0.5).astype(dtype),
          (jax.random.normal(keys[4], (width,)) * 0.1).astype(dtype),
          jax.random.normal(keys[5], (rows, width), jnp.float32))


def _step(impl: str, blocks: fused.Blocks):
  def loss(x, w1, b1, w2, b2, probe):
    out = fused.mlp(x, w1, b1, w2, b2, impl=impl, blocks=blocks)
    return jnp.sum(out.astype(jnp.float32) * probe)
  return jax.jit(jax.value_and_grad(loss, argnums=range(5)))


def _errors(got, want) -> dict:
  names = ["loss", "x", "w1", "b1", "w2", "b2"]
  flat = [got[0]] + list(got[1]), [want[0]] + list(want[1])
  return {n: float(jnp.max(jnp.abs(g.astype(jnp.float32) - w)) / jnp.max(jnp.abs(w)))
          for n, g, w in zip(names, *flat)}


def benchmark(rows: int, width: int, ratio: int, settings: list[fused.Blocks], repeats: int
              ) -> dict:
  args = _inputs(rows, width, ratio, jnp.bfloat16)
  reference = _step("xla", fused.Blocks())(*(a.astype(jnp.float32) for a in args))
  flops = 3 * 2 * 2 * rows * width * ratio * width
  runs = []
  for impl, blocks in [("xla", None)] + [("pallas", b) for b in settings]:
    step = _step(impl, blocks or fused.Blocks())
    try:
      seconds, compile_s = median_seconds(lambda: step(*args), repeats)
    except Exception as e:  # a tile setting Triton cannot compile: say so, go on
      runs.append({"impl": impl, "blocks": blocks and dataclasses.asdict(blocks),
                   "error": f"{type(e).__name__}: {str(e)[:300]}"})
      continue
    runs.append({"impl": impl, "blocks": blocks and dataclasses.asdict(blocks), "ms": seconds * 1e3,
                 "tflops_per_s": flops / seconds / 1e12, "compile_s": compile_s,
                 "relative_error": _errors(step(*args), reference)})
    print(json.dumps(runs[-1]), flush=True)
  return {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "rows": rows,
          "width": width, "hidden": ratio * width, "dtype": "bfloat16",
          "flop_per_step": flops, "runs": runs}


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--rows", type=int, default=81920,
                      help="tokens (IRASim-XL/2 at batch 16: 16 x 16 frames x 320 patches)")
  parser.add_argument("--width", type=int, default=1152)
  parser.add_argument("--ratio", type=int, default=4, help="hidden width / width")
  parser.add_argument("--blocks", action="append", default=None,
                      help="rows,cols,depth,warps,stages (repeat; default: the kernel's default)")
  parser.add_argument("--repeats", type=int, default=10)
  parser.add_argument("--out", default=None)
  args = parser.parse_args()
  settings = [fused.Blocks(*(int(v) for v in s.split(","))) for s in args.blocks or []]
  result = benchmark(args.rows, args.width, args.ratio, settings or [fused.Blocks()],
                     args.repeats)
  print(json.dumps(result, indent=2))
  if args.out:
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
      json.dump(result, f, indent=2)


if __name__ == "__main__":
  main()
