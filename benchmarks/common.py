"""Shared pieces of the model benchmarks: config arguments, timing and the JSON result.

Config overrides are ``--config.KEY=VALUE``, as for the ``wmjax`` commands
(:func:`wmjax.config.parse_args_with_overrides`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import statistics
import time

import jax

from wmjax.config import parse_args_with_overrides


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--config", required=True, help="config file, optionally file.py:arg")
  parser.add_argument("--out", default=None,
                      help="JSON path (default benchmarks/results/<kind>-<name>-<platform>.json)")


def add_kernel_arguments(parser: argparse.ArgumentParser) -> None:
  """``--mlp_blocks``: the tiles of the fused MLP kernels (``model.mlp_kernel=pallas``)."""
  parser.add_argument("--mlp_blocks", default=None, metavar="R,C,D,WARPS,STAGES",
                      help="tiles of the fused MLP kernels (model.mlp_kernel=pallas), the "
                           "config's model.mlp_blocks; default: wmjax.nn.kernels.mlp.Blocks()")


def kernel_overrides(args: argparse.Namespace) -> tuple[list[str], dict]:
  """``--mlp_blocks`` as the config override of the fused MLP kernels' tiles
  (``model.mlp_blocks``), and the tiles the model gets (the defaults without it)."""
  from wmjax.nn.kernels import mlp
  tiles = tuple(int(v) for v in args.mlp_blocks.split(",")) if args.mlp_blocks else ()
  return ([f"model.mlp_blocks={tiles}"] if tiles else []), dataclasses.asdict(mlp.Blocks(*tiles))


def parse_args(parser: argparse.ArgumentParser) -> argparse.Namespace:
  """The parser's arguments, with the ``--config.KEY=VALUE`` overrides as ``args.overrides``."""
  args, args.overrides = parse_args_with_overrides(parser)
  return args


def write_result(kind: str, result: dict, args: argparse.Namespace) -> str:
  """Print ``result`` and save it as JSON (``args.out`` or a name from config and platform)."""
  print(json.dumps(result, indent=2))
  tag = result["name"].replace("/", "_") + ("-custom" if args.overrides else "")
  out = args.out or os.path.join(os.path.dirname(__file__), "results",
                                 f"{kind}-{tag}-{jax.default_backend()}-b{args.batch}.json")
  os.makedirs(os.path.dirname(out), exist_ok=True)
  with open(out, "w") as f:
    json.dump(result, f, indent=2)
  print(f"wrote {out}")
  return out


def median_seconds(fn, repeats: int) -> tuple[float, float]:
  """(median seconds of ``repeats`` calls of ``fn`` after a first, compiling call; that call's
  seconds)."""
  start = time.perf_counter()
  jax.block_until_ready(fn())
  compile_s = time.perf_counter() - start
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - start)
  return statistics.median(times), compile_s


def compiled_memory(compiled) -> dict:
  """Per-device GiB of a compiled program as XLA plans it (arguments, outputs, temporaries;
  aliased = donated arguments reused as outputs), or {} where the backend gives none."""
  analysis = compiled.memory_analysis()
  if analysis is None:
    return {}
  gib = lambda n: round(n / 1024 ** 3, 3)
  args, out, temp = (analysis.argument_size_in_bytes, analysis.output_size_in_bytes,
                     analysis.temp_size_in_bytes)
  alias = analysis.alias_size_in_bytes
  return {"arguments_gib": gib(args), "outputs_gib": gib(out), "temp_gib": gib(temp),
          "aliased_gib": gib(alias), "total_gib": gib(args + out - alias + temp)}


def check_fits(memory: dict) -> None:
  """SystemExit before the first step when the compiled program (``compiled_memory``) is larger
  than what JAX's allocator may take on the first device (GPU / TPU; CPU reports no limit)."""
  limit = (jax.devices()[0].memory_stats() or {}).get("bytes_limit")
  if limit and memory and memory["total_gib"] * 1024 ** 3 > limit:
    raise SystemExit(
        f"the compiled step needs {memory['total_gib']:.1f} GiB per device (arguments "
        f"{memory['arguments_gib']:.1f} + temporaries {memory['temp_gib']:.1f}) but the allocator "
        f"may use {limit / 1024 ** 3:.1f} GiB: use a smaller --batch or model.remat='full' (or "
        f"raise XLA_PYTHON_CLIENT_MEM_FRACTION)")


def peak_memory() -> dict:
  """Peak memory so far: the first device's allocator peak (GPU / TPU; None on CPU, whose
  allocator keeps no statistics) and this process's peak resident set (host)."""
  stats = jax.devices()[0].memory_stats() or {}
  return {"peak_device_bytes": stats.get("peak_bytes_in_use"),
          "peak_host_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}
