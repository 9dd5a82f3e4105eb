"""``wmjax compile``: a config's train step or rollout block compiled for a device target it
need not run on: memory, whether it fits, FLOPs."""

from __future__ import annotations

import json

from wmjax.cli import common
from wmjax.config import load_config


def run(args, extra) -> int:
  """Compile the exact sharded train step (or one jitted rollout block) of a config for a target,
  without its hardware, and print per-device memory from XLA (arguments, outputs, temporaries,
  total), the device's memory and whether it fits, the mesh, XLA's and the analytic FLOPs, the
  compile time and, on a card or TPU of known rates, its predicted time per step or block (matmul
  FLOPs and the bytes of the other kernels, from the optimized HLO; fitted on an H200). When a
  train step does not fit, also the setting train.auto_fit would choose: of remat none ->
  dots_elementwise -> dots -> full with the fewest gradient-accumulation micro-batches that fit,
  the one predicted fastest.
  Targets: h100[:N], h200[:N], a100[:N] (needs JAX's CUDA plugin, no GPU), TPU topologies such as
  v5p:2x2x1, v5p:4x4x4, v5e:4x4, v6e:2x2 (needs libtpu, no TPU) and cpu:N. GPU memory counts
  XLA_PYTHON_CLIENT_MEM_FRACTION (default 0.75) of the card. Exits 1 when the config's own setting
  does not fit."""
  import jax

  from wmjax.train import aot, fit
  name, _, count = args.target.partition(":")
  if name == "cpu" and count.isdigit():  # simulated devices, before the backend starts
    jax.config.update("jax_num_cpu_devices", int(count))
  config = load_config(args.config, common.overrides(extra))
  try:
    target = fit.parse_target(args.target)
  except ValueError as e:
    raise SystemExit(f"wmjax compile: {e}") from e
  budget = None if args.budget_gib is None else int(args.budget_gib * fit.GIB)
  report = aot.compile_report(config, target, args.what, args.batch, budget,
                              log=lambda line: print(line, flush=True))
  print(fit.describe(report))
  if "auto_fit" in report:
    choice = report["auto_fit"]
    speed = ("" if choice["predicted_ms"] is None else
             f", predicted {choice['predicted_ms']:.0f} ms a step")
    print(f"auto_fit would choose model.remat={choice['remat']!r} "
          f"optim.grad_accum={choice['grad_accum']} ({choice['total_gib']:.3g} GiB per device"
          f"{speed})")
  print(json.dumps(report, indent=2))
  if args.out:
    with open(args.out, "w") as f:
      json.dump(report, f, indent=2)
  return 1 if report["fits"] is False else 0


def add_parser(sub) -> None:
  """The ``compile`` command."""
  parser = sub.add_parser("compile", help="compile a train step or rollout for a device target "
                                          "(no hardware needed): memory, fits, FLOPs",
                          description=run.__doc__)
  parser.add_argument("--config", required=True, help=common.CONFIG_HELP)
  parser.add_argument("--target", required=True,
                      help="h100[:N] | h200[:N] | a100[:N] | TPU topology (v5p:2x2x1, v5e:4x4, "
                           "...) | cpu:N")
  parser.add_argument("--what", choices=["train", "rollout"], default="train",
                      help="the train step (default) or one rollout block")
  parser.add_argument("--batch", type=int, default=None,
                      help="global batch (default: the config's batch_size; rollout: 8)")
  parser.add_argument("--budget_gib", type=float, default=None,
                      help="memory per device to fit (default: the target's usable memory)")
  parser.add_argument("--out", default=None, help="also write the report as JSON here")
  common.register(parser, run, takes_overrides=True, host_only=True)
