"""The kernels of a compiled program, from its optimized HLO, counted per execution: how many of
each class run and how many bytes they move, with its transposes and copies listed one by one.

  python benchmarks/hlo_ops.py --config configs/irasim.py:XL --target h100 --batch 16 \
      --config.model.dtype=bfloat16 --config.model.attention_impl=auto \
      --config.model.remat=dots [--save_hlo /tmp/xl.hlo] [--top 40] [--json [FILE]]
  python benchmarks/hlo_ops.py --hlo /tmp/xl.hlo [--summary]

The first form compiles the train step of a config for a device target as ``wmjax compile`` does
(:func:`wmjax.train.context.compile_step`; no hardware needed) and reads ``compiled.as_text()``; the
second reads HLO text saved before. For an H100 target without a GPU, set
``XLA_FLAGS="--xla_gpu_enable_triton_gemm=false --xla_gpu_autotune_level=0"``: without autotuning
the Triton GEMM emitter can fail to tile some matmuls.

The classes, and how bytes and FLOPs are counted (``while`` bodies once per iteration), are
those of :mod:`wmjax.train.hlo_cost`, which this script prints as a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from wmjax.train.hlo_cost import Row, analyze, summary


def report(rows: list[Row], top: int) -> str:
  """The ``top`` rows, most bytes first (none for ``top=0``), then the summary by class."""
  lines = []
  if top:
    lines.append(f"{'class':<12}{'count':>6}{'GB':>9}  {'shape':<44}op")
    for row in rows[:top]:
      lines.append(f"{row.cls:<12}{row.count:>6}{row.moved / 1e9:>9.3f}  {row.shape:<44}{row.op}")
    lines.append("")
  lines.append(f"{'class':<15}{'kernels':>8}{'GB':>10}{'TFLOP':>9}")
  for cls, s in summary(rows).items():
    lines.append(f"{cls:<15}{s['kernels']:>8}{s['gb']:>10.3f}{s['tflop']:>9.1f}")
  return "\n".join(lines)


def compiled_text(config_spec: str, overrides: list[str], target_spec: str, batch: int | None
                  ) -> tuple[str, dict]:
  """Optimized HLO text and memory report of a config's train step compiled for a target."""
  import jax
  jax.config.update("jax_platforms", "cpu")
  from wmjax.config import load_config
  from wmjax.train import context, fit
  config = load_config(config_spec, overrides)
  compiled, memory = context.compile_step(
      context.build_context(config, fit.parse_target(target_spec)), batch)
  return compiled.as_text(), memory


def main() -> None:
  from wmjax.config import parse_args_with_overrides
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--hlo", default=None, help="read this HLO text instead of compiling")
  parser.add_argument("--config", default=None)
  parser.add_argument("--target", default="h100")
  parser.add_argument("--batch", type=int, default=None)
  parser.add_argument("--save_hlo", default=None, help="also write the compiled HLO text here")
  parser.add_argument("--top", type=int, default=40, help="table rows (most bytes first)")
  parser.add_argument("--summary", action="store_true", help="print the summary by class only")
  parser.add_argument("--json", nargs="?", const="-", default=None, metavar="FILE",
                      help="also write the summary and the top rows as JSON to FILE (stdout "
                           "without FILE)")
  args, overrides = parse_args_with_overrides(parser)
  memory = None
  if args.hlo:
    with open(args.hlo) as f:
      text = f.read()
  elif args.config:
    text, memory = compiled_text(args.config, overrides, args.target, args.batch)
    if args.save_hlo:
      with open(args.save_hlo, "w") as f:
        f.write(text)
  else:
    sys.exit("hlo_ops: give --hlo FILE or --config CONFIG")
  rows = analyze(text)
  print(report(rows, 0 if args.summary else args.top))
  if memory is not None:
    print(f"compiled memory per device: {memory['total_gib']:.2f} GiB "
          f"(temporaries {memory['temp_gib']:.2f} GiB)")
  if args.json:
    found = json.dumps({"summary": summary(rows),
                        "rows": [dataclasses.asdict(row) for row in rows[:args.top]],
                        "total_gib": None if memory is None else memory["total_gib"]}, indent=1)
    if args.json == "-":
      print(found)
    else:
      with open(args.json, "w") as f:
        f.write(found + "\n")


if __name__ == "__main__":
  main()
