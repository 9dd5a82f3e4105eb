"""The ``wmjax`` command line.

  wmjax info --config configs/irasim.py:XL [--config.key=value ...]

Config overrides use ``--config.dotted.key=value`` with Python literal values.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax
import numpy as np


def _config_from_args(args, extra: list[str]):
  from wmjax.config import load_config
  bad = [a for a in extra if not a.startswith("--config.")]
  if bad:
    raise SystemExit(f"wmjax: unrecognised arguments {bad}; overrides look like --config.key=value")
  return load_config(args.config, extra)


def cmd_info(args, extra) -> int:
  """Parameter count, forward FLOPs and sampling cost of a config, without allocating the model."""
  from wmjax.nn import forward_flops
  from wmjax.rollout import WorldModel

  config = _config_from_args(args, extra)
  wm = WorldModel.from_config(config)
  net = wm.network
  h, w, c = config.frame_shape
  frames = config.rollout.context + config.rollout.horizon
  shapes = jax.eval_shape(lambda: wm.init(jax.random.key(0), (h, w, c), frames=frames))
  params = sum(int(np.prod(p.shape)) for p in jax.tree.leaves(shapes))
  flops = forward_flops(net, 1, frames, h, w)
  calls = wm.sampler.model_calls(config.rollout.horizon)
  guidance = 2 if wm.sampler.guidance_scale != 1.0 else 1
  info = {
      "name": config.get("name", args.config),
      "parameters": params,
      "parameter_bytes_fp32": 4 * params,
      "frame_shape": [h, w, c],
      "window_frames": frames,
      "forward_gflop_per_window": flops / 1e9,
      "model_calls_per_block": calls * guidance,
      "gflop_per_generated_frame": flops * calls * guidance / config.rollout.horizon / 1e9,
  }
  print(json.dumps(info, indent=2))
  return 0


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(
      prog="wmjax", description="Action-conditioned video world models for robot manipulation.")
  sub = parser.add_subparsers(dest="command", required=True)
  info = sub.add_parser("info", help="parameter count and FLOPs of a config (no allocation)",
                        description=cmd_info.__doc__)
  info.add_argument("--config", required=True, help="config file, optionally file.py:arg")
  info.set_defaults(func=cmd_info)
  args, extra = parser.parse_known_args(argv)
  return args.func(args, extra)


if __name__ == "__main__":
  sys.exit(main())
