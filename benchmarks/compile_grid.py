"""Compiled per-device memory of train steps over a grid of batch sizes and remat settings, for a
device target without its hardware (``wmjax.train.fit``); one JSON line per setting.

  python benchmarks/compile_grid.py --config configs/irasim.py:XL --target h100 \
      --batch 8 --batch 16 --remat none --remat dots --config.model.dtype=bfloat16 \
      [--out benchmarks/results/compile-irasim-h100.jsonl]

``--largest`` instead finds, per remat setting, the largest global batch (a multiple of the
data-parallel size, doubling from it) whose step fits the target's memory.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax

from wmjax.config import load_config, parse_args_with_overrides
from wmjax.train import fit


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--config", required=True)
  parser.add_argument("--target", required=True)
  parser.add_argument("--batch", type=int, action="append", default=[])
  parser.add_argument("--remat", action="append", default=[], choices=fit.REMAT_LADDER)
  parser.add_argument("--largest", action="store_true")
  parser.add_argument("--out", default=None)
  args, overrides = parse_args_with_overrides(parser)
  jax.config.update("jax_platforms", "cpu")
  name, _, count = args.target.partition(":")
  if name == "cpu":
    jax.config.update("jax_num_cpu_devices", int(count or 1))
  config = load_config(args.config, overrides)
  target = fit.parse_target(args.target)
  out = open(args.out, "a") if args.out else None

  def record(report):
    line = json.dumps({"config": args.config, "overrides": overrides, **report})
    print(line, flush=True)
    if out:
      out.write(line + "\n")
      out.flush()

  for remat in args.remat or list(fit.REMAT_LADDER):
    setting = fit.with_setting(config, remat, 1)
    if not args.largest:
      for batch in args.batch or [config.batch_size]:
        record(fit.compile_train(setting, target, batch))
      continue
    mesh_devices = len(target.devices) // (config.mesh[2] if config.mesh[2] > 0 else 1)
    batch = mesh_devices
    while True:
      report = fit.compile_train(setting, target, batch)
      record(report)
      if not report["fits"]:
        break
      batch *= 2
  if out:
    out.close()


if __name__ == "__main__":
  sys.exit(main())
