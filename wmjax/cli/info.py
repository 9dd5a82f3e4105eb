"""``wmjax info``: what a config costs (parameters, FLOPs, memory), with nothing allocated."""

from __future__ import annotations

import json

from wmjax.cli import common
from wmjax.config import load_config


def run(args, extra) -> int:
  """Parameter count, forward FLOPs, sampling cost and a per-device training-memory estimate of a
  config, without allocating the model."""
  from wmjax.train.info import config_info
  config = load_config(args.config, common.overrides(extra))
  print(json.dumps(config_info(config, args.devices, name=args.config), indent=2))
  return 0


def add_parser(sub) -> None:
  """The ``info`` command."""
  parser = sub.add_parser("info", help="parameter count and FLOPs of a config (no allocation)",
                          description=run.__doc__)
  parser.add_argument("--config", required=True, help=common.CONFIG_HELP)
  parser.add_argument("--devices", type=int, default=None,
                      help="devices to estimate training memory for (default: this machine's)")
  common.register(parser, run, takes_overrides=True, host_only=True)
