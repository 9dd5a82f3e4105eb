"""What the command modules share: registering a command, its ``--config.KEY=VALUE`` overrides
and keeping host-only commands off accelerators."""

from __future__ import annotations

import argparse
import os

from wmjax.config import OVERRIDES_HELP, split_overrides

CONFIG_HELP = "config file, optionally file.py:arg"
WORKDIR_HELP = "training workdir with checkpoints/"


def overrides(extra: list[str]) -> list[str]:
  """The ``--config.KEY=VALUE`` overrides of a command (the shared syntax, wmjax.config)."""
  found, bad = split_overrides(extra)
  if bad:
    raise SystemExit(f"wmjax: unrecognised arguments {bad}; overrides look like --config.KEY=VALUE")
  return found


def register(parser: argparse.ArgumentParser, func, takes_overrides: bool = False,
             host_only: bool = False, passes_on: bool = False) -> None:
  """``parser`` runs ``func(args, extra)``; only commands with ``takes_overrides`` take
  --config.KEY=VALUE; ``host_only`` commands do no accelerator work and run JAX on the CPU
  alone; ``passes_on`` commands get the arguments they do not know themselves in ``extra``."""
  parser.set_defaults(func=func, takes_overrides=takes_overrides, command_parser=parser,
                      host_only=host_only, passes_on=passes_on)
  if takes_overrides and not parser.epilog:
    parser.epilog = OVERRIDES_HELP


def inference_model(workdir: str, args, extra: list[str]):
  """The checkpoint of ``workdir`` that ``args`` choose (``--step``, ``--params``, ``--param_dtype``
  where the command has it) with the command's overrides; a ``model.fp8_matmuls`` model with
  float8 scales calibrated on its training split where that can be read (said in one line;
  :func:`wmjax.eval.calibration.with_float8_scales`)."""
  import jax

  from wmjax.eval.calibration import with_float8_scales
  from wmjax.model import load_model
  model = load_model(workdir, step=args.step, params=args.params, overrides=overrides(extra),
                     param_dtype=getattr(args, "param_dtype", "float32"))
  model, float8 = with_float8_scales(model, jax.random.key(0))
  if float8:
    print(f"model.fp8_matmuls: {float8}", flush=True)
  return model


def checkpoint_args(parser: argparse.ArgumentParser, dtype: bool = True) -> None:
  """--step, --params (and --param_dtype) choosing what of a workdir's checkpoints is loaded."""
  parser.add_argument("--step", type=int, default=None, help="checkpoint (default: latest)")
  parser.add_argument("--params", choices=["ema", "raw"], default="ema")
  if dtype:
    parser.add_argument("--param_dtype", choices=["float32", "bfloat16"], default="float32",
                        help="parameters' dtype for inference (compute: --config.model.dtype)")


def host_only() -> None:
  """Keep JAX off accelerators (``JAX_PLATFORMS=cpu``) before any backend starts: a command that
  does CPU work must not take a GPU's memory from a training job beside it."""
  import jax
  os.environ["JAX_PLATFORMS"] = "cpu"
  jax.config.update("jax_platforms", "cpu")
