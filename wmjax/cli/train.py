"""``wmjax train``: train (or resume) a world model in a workdir."""

from __future__ import annotations

import json
import os

from wmjax.cli import common
from wmjax.config import OVERRIDES_HELP, load_config

RESUME_HELP = ("Rerunning in a WORKDIR with checkpoints resumes from the newest one that reads "
               "back (a damaged newer one is moved to WORKDIR/damaged_checkpoints with a "
               "warning). The config must then match the checkpoint's, except for changes that "
               "are always accepted: {safe}; any other change stops with the list of differing "
               "keys unless --allow_config_change names them (or their section); changes of "
               "parameter shapes are always refused. SIGTERM or Ctrl-C save a checkpoint and "
               "exit with 143 / 130; a NaN / inf loss or a failed save exits with 1.")


def maybe_initialize_distributed(args) -> None:
  """``jax.distributed.initialize`` when several processes take part (flags, SLURM or TPU pods)."""
  import jax
  explicit = args.coordinator_address is not None
  slurm = int(os.environ.get("SLURM_NTASKS", "1")) > 1
  if not (explicit or slurm or os.environ.get("TPU_WORKER_HOSTNAMES")):
    return
  if jax.config.jax_platforms in (None, "", "cpu") and not os.environ.get("TPU_WORKER_HOSTNAMES"):
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
  if explicit:
    jax.distributed.initialize(args.coordinator_address, args.num_processes, args.process_id)
  else:
    jax.distributed.initialize()


def run(args, extra) -> int:
  """Train a world model in WORKDIR, resuming from its latest checkpoint if it has one."""
  import jax

  from wmjax.train.loop import train
  maybe_initialize_distributed(args)
  config = load_config(args.config, common.overrides(extra))
  allow = [k for item in args.allow_config_change for k in item.split(",") if k.strip()]
  _, result = train(config, args.workdir, allow_config_change=allow)
  if jax.process_index() == 0:
    print(json.dumps(result, indent=2))
  # stopped by a signal before the end: the conventional 128 + signal (143 SIGTERM, 130 SIGINT)
  return 128 + result["signal"] if "signal" in result else 0


def add_parser(sub) -> None:
  """The ``train`` command."""
  from wmjax.train.resume import SAFE_ON_RESUME
  parser = sub.add_parser("train", help="train (or resume) a world model in a workdir",
                          description=run.__doc__)
  parser.add_argument("--config", required=True, help=common.CONFIG_HELP)
  parser.add_argument("--workdir", required=True, help="checkpoints, logs, videos and metrics")
  parser.add_argument("--coordinator_address", default=None,
                      help="host:port of process 0, for a multi-process run started by hand")
  parser.add_argument("--num_processes", type=int, default=None)
  parser.add_argument("--process_id", type=int, default=None)
  parser.add_argument("--allow_config_change", action="append", default=[], metavar="KEY[,KEY]",
                      help="on resume, accept these changed config keys (or whole sections, e.g. "
                           "optim); repeatable")
  common.register(parser, run, takes_overrides=True)
  parser.epilog = OVERRIDES_HELP + " " + RESUME_HELP.format(safe=", ".join(SAFE_ON_RESUME))
