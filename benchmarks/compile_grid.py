"""Compiled per-device memory of train steps over a grid of batch sizes and remat settings, for a
device target without its hardware (``wmjax.train.aot``); one JSON line per setting.

  python benchmarks/compile_grid.py --config configs/irasim.py:XL --target h100 \
      --batch 8 --batch 16 --remat none --remat dots --config.model.dtype=bfloat16 \
      [--out benchmarks/results/compile-irasim-h100.jsonl]

``--largest`` instead finds, per remat setting, the largest global batch (the data-parallel size
times a power of two) whose step fits the target's memory: from ``--start`` (default: one sample
per device) it doubles while the step fits, or halves until it does. Each line also carries the
per-device batch.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax

from wmjax.config import load_config, parse_args_with_overrides
from wmjax.train import aot, fit
from wmjax.train.context import with_setting


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--config", required=True)
  parser.add_argument("--target", required=True)
  parser.add_argument("--batch", type=int, action="append", default=[])
  parser.add_argument("--remat", action="append", default=[], choices=fit.REMAT_LADDER)
  parser.add_argument("--largest", action="store_true")
  parser.add_argument("--start", type=int, default=None,
                      help="--largest: per-device batch to start from (a power of two; default 1)")
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
    data_parallel = report["mesh"]["data"] * report["mesh"]["fsdp"]
    line = json.dumps({"config": args.config, "overrides": overrides,
                       "per_device_batch": report["batch"] / data_parallel, **report})
    print(line, flush=True)
    if out:
      out.write(line + "\n")
      out.flush()
    return report

  mesh_devices = len(target.devices) // (config.mesh[2] if config.mesh[2] > 0 else 1)
  for remat in args.remat or list(fit.REMAT_LADDER):
    setting = with_setting(config, remat, 1)
    if not args.largest:
      for batch in args.batch or [config.batch_size]:
        record(aot.compile_train(setting, target, batch))
      continue
    per_device = args.start or 1
    fits = {}  # per-device batch -> fits
    while True:
      report = aot.compile_train(setting, target, per_device * mesh_devices)
      fits[per_device] = record(report)["fits"]
      if fits[per_device] and fits.get(per_device * 2) is False:
        break
      if not fits[per_device] and (per_device == 1 or fits.get(per_device // 2)):
        break
      per_device = per_device * 2 if fits[per_device] else per_device // 2
    largest = max((b for b, ok in fits.items() if ok), default=0)
    print(f"# {args.config} on {args.target}, remat={remat}: largest per-device batch that fits: "
          f"{largest or 'none (1 does not fit)'}", flush=True)
  if out:
    out.close()


if __name__ == "__main__":
  sys.exit(main())
