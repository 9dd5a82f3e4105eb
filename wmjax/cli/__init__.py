"""The ``wmjax`` command line: one module per command group, each parsing its arguments, calling
the library and printing the result.

    wmjax train --config configs/gridworld.py --workdir DIR [--config.key=value ...]   (train)
    wmjax evaluate --workdir DIR [--split test] [--protocols short,long,sweep]        (evaluate)
    wmjax rollout --workdir DIR --frames FILE [FILE ...] --actions FILE --out DIR      (rollout)
    wmjax eval-policy --workdir DIR [--policy push:0.1 ...] [--reward coverage|...]   (pusht)
    wmjax eval-policy --workdir DIR --reader DIR [--policy expert:0.2 ...]   (pusht, MetaWorld)
    wmjax plan --workdir DIR [--candidates 1,5,10,50] [--proposal push:0.2]            (pusht)
    wmjax clone-policy --workdir DIR --out POLICY [--task reach]                      (policy)
    wmjax improve --workdir DIR --policy POLICY --out NEW [--rounds 3]                 (policy)
    wmjax launch --num_processes 2 -- train --config configs/gridworld.py --workdir DIR (launch)
    wmjax info --config configs/irasim.py:XL [--config.key=value ...]                  (info)
    wmjax compile --config configs/irasim.py:XL --target h100|v5p:2x2x1|cpu:N          (compile)
    wmjax data prepare gridworld|pusht|metaworld --data_dir DIR [--task T --views A,B ...] (data)
    wmjax data convert SRC_BUILDER_DIR DST_DIR
    wmjax data encode --config FILE --out DIR [--splits train,test]
    wmjax data stats BUILDER_DIR [--split train] [--recompute]
    wmjax data inspect BUILDER_DIR
    wmjax data import lerobot SRC OUT [--camera KEY]
    wmjax data import irasim SRC OUT [--dataset rt1|bridge|languagetable] [--camera N]
    wmjax data import wpe SRC OUT [--subsets rt_1,bridge_v2]
    wmjax import irasim CKPT.pt --workdir DIR [--dataset rt1|bridge] [--weights ema|model] (import)

``eval-policy`` checks a Push-T or a MetaWorld world model against its simulator; ``plan`` is
Push-T's. ``clone-policy`` and ``improve`` train a learnable policy on a control task of the
model's task module (the gridworld's ``reach``, Push-T's ``push``) and check it in the task's true
environment.
Config overrides use ``--config.dotted.key=value`` with Python literal values (train, evaluate,
rollout, eval-policy, plan, info, compile, data encode); an unknown key or flag is an error.
info, compile and the data commands but encode run JAX on the CPU only.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys

from wmjax.cli import common

DESCRIPTION = ("Action-conditioned video world models: train, evaluate and roll out; eval-policy "
               "and plan check a Push-T model against its simulator; clone-policy and improve "
               "train a policy inside a model.")


def build_parser() -> argparse.ArgumentParser:
  """The ``wmjax`` parser with every command group's subcommands."""
  from wmjax.cli import compile as compile_
  from wmjax.cli import data, evaluate, importer, info, launch, policy, pusht, rollout, train
  parser = argparse.ArgumentParser(prog="wmjax", description=DESCRIPTION)
  parser.add_argument("--debug", action="store_true",
                      help="show the traceback of an error instead of one line (anywhere "
                           "on the command line; also WMJAX_DEBUG=1)")
  sub = parser.add_subparsers(dest="command", required=True)
  for group in (train, evaluate, rollout, pusht, policy, launch, info, compile_, data,
                importer):
    group.add_parser(sub)
  return parser


# What a user's input can cause (a bad path, value, split, key, a missing optional package): one
# line on stderr and exit 2, as a config error; with --debug or WMJAX_DEBUG=1 the traceback.
USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, ImportError)


@contextlib.contextmanager
def _library_log_shown():
  """While a command runs, the library's own messages from INFO up (a codec's or a policy's fitting
  progress, skipped episodes) are shown: through the handlers already installed (a library that
  configured the root logger, or the caller), else on stderr as ``wmjax.module: message``."""
  logger = logging.getLogger("wmjax")
  level = logger.level
  handler = None
  if not logger.hasHandlers():
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    logger.addHandler(handler)
  logger.setLevel(logging.INFO)
  try:
    yield
  finally:
    if handler is not None:
      logger.removeHandler(handler)
    logger.setLevel(level)


def main(argv: list[str] | None = None) -> int:
  """Run one ``wmjax`` command; its exit status. A config error or bad input (:data:`USER_ERRORS`)
  exits 2 and a run error (a condition the message explains) 1, each with one line on stderr
  instead of a traceback (``--debug`` or ``WMJAX_DEBUG=1`` shows it)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  debug = "--debug" in argv or os.environ.get("WMJAX_DEBUG") == "1"
  args, extra = build_parser().parse_known_args([a for a in argv if a != "--debug"])
  if not args.passes_on:
    bad = [a for a in extra if not (args.takes_overrides and a.startswith("--config."))]
    bad += [a for a in extra if a.startswith("--config.") and "=" not in a]
    if bad:
      args.command_parser.error(
          f"unrecognized arguments: {' '.join(bad)}"
          + ("; config overrides look like --config.KEY=VALUE" if args.takes_overrides else ""))
  if args.host_only:
    common.host_only()
  from wmjax.config import ConfigError
  from wmjax.errors import RunError
  try:
    with _library_log_shown():
      return args.func(args, extra)
  except (ConfigError, RunError) as e:
    print(f"{args.command_parser.prog}: {e}", file=sys.stderr)
    return 2 if isinstance(e, ConfigError) else 1
  except USER_ERRORS as e:
    if debug:
      raise
    message = " ".join(str(e).split()) or type(e).__name__
    print(f"{args.command_parser.prog}: {message} (--debug shows the traceback)", file=sys.stderr)
    return 2
  except Exception as e:  # TensorFlow's DataLossError, without importing TensorFlow to name it
    if debug or type(e).__name__ != "DataLossError":
      raise
    lines = str(e).strip().splitlines()
    print(f"{args.command_parser.prog}: the data is damaged: a TFRecord shard is cut short or "
          f"corrupted ({lines[0] if lines else 'DataLossError'}); copy, convert or import it "
          f"again (--debug shows the traceback)", file=sys.stderr)
    return 2
