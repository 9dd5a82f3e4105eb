"""``wmjax launch``: a wmjax command as several local processes joined by jax.distributed."""

from __future__ import annotations

import argparse
import sys

from wmjax.cli import common


def run(args, extra) -> int:
  """Run a wmjax command (e.g. train) as several processes on this machine, joined by
  jax.distributed: CPU processes with simulated devices, or one slice of the GPUs each."""
  from wmjax.launch import launch_local
  command = list(args.command) + list(extra)
  if command[:1] == ["--"]:
    command = command[1:]
  if not command:
    raise SystemExit("wmjax launch: give the command after --, e.g. -- train --config F --workdir D")
  return launch_local([sys.executable, "-m", "wmjax.cli"] + command, args.num_processes,
                      platform=args.platform, devices_per_process=args.devices_per_process,
                      port=args.port)


def add_parser(sub) -> None:
  """The ``launch`` command; it passes every argument after ``--`` on to its command."""
  parser = sub.add_parser("launch", help="run a command as N local processes (jax.distributed)",
                          description=run.__doc__)
  parser.add_argument("--num_processes", type=int, required=True)
  parser.add_argument("--platform", choices=["cpu", "gpu"], default="cpu")
  parser.add_argument("--devices_per_process", type=int, default=1,
                      help="simulated CPU devices, or GPUs, per process")
  parser.add_argument("--port", type=int, default=None, help="coordinator port (default: free)")
  parser.add_argument("command", nargs=argparse.REMAINDER,
                      help="-- followed by the wmjax command, e.g. -- train --config F ...")
  common.register(parser, run, passes_on=True)
