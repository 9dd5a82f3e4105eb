"""The ``wmjax`` command line.

  wmjax train --config configs/gridworld.py --workdir DIR [--config.key=value ...]
  wmjax evaluate --workdir DIR [--split test] [--protocols short,long,sweep] [--config.key=value]
  wmjax rollout --workdir DIR --frames FILE [FILE ...] --actions FILE --out DIR
  wmjax eval-policy --workdir DIR [--policy push:0.1 ...] [--reward coverage|vlm|...]
  wmjax plan --workdir DIR [--candidates 1,5,10,50] [--proposal push:0.2]
  wmjax launch --num_processes 2 -- train --config configs/gridworld.py --workdir DIR
  wmjax info --config configs/irasim.py:XL [--config.key=value ...]
  wmjax compile --config configs/irasim.py:XL --target h100|v5p:2x2x1|cpu:N [--batch B] [--out F]
  wmjax data prepare gridworld|pusht --data_dir DIR [--num_squares N ...]
  wmjax data convert SRC_BUILDER_DIR DST_DIR
  wmjax data encode --config FILE --out DIR [--splits train,test]
  wmjax data stats BUILDER_DIR [--split train] [--recompute]
  wmjax data inspect BUILDER_DIR
  wmjax data import lerobot SRC OUT [--camera KEY]

Config overrides use ``--config.dotted.key=value`` with Python literal values (train, evaluate,
rollout, eval-policy, plan, info, compile, data encode); an unknown key or flag is an error.
info, compile and the data commands but encode run JAX on the CPU only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

import jax
import numpy as np

from wmjax.config import OVERRIDES_HELP, split_overrides

RESUME_HELP = ("Rerunning in a WORKDIR with checkpoints resumes from the newest one that reads "
               "back (a damaged newer one is moved to WORKDIR/damaged_checkpoints with a "
               "warning). The config must then match the checkpoint's, except for changes that "
               "are always accepted: {safe}; any other change stops with the list of differing "
               "keys unless --allow_config_change names them (or their section); changes of "
               "parameter shapes are always refused. SIGTERM or Ctrl-C save a checkpoint and "
               "exit with 143 / 130; a NaN / inf loss or a failed save exits with 1.")


def _overrides(extra: list[str]) -> list[str]:
  """The ``--config.KEY=VALUE`` overrides of a command (the shared syntax, wmjax.config)."""
  overrides, bad = split_overrides(extra)
  if bad:
    raise SystemExit(f"wmjax: unrecognised arguments {bad}; overrides look like --config.KEY=VALUE")
  return overrides


def _config_from_args(args, extra: list[str]):
  from wmjax.config import load_config
  return load_config(args.config, _overrides(extra))


def _register(parser: argparse.ArgumentParser, func, overrides: bool = False,
              host_only: bool = False) -> None:
  """``parser`` runs ``func``; only commands with ``overrides`` take --config.KEY=VALUE;
  ``host_only`` commands do no accelerator work and run JAX on the CPU alone."""
  parser.set_defaults(func=func, takes_overrides=overrides, command_parser=parser,
                      host_only=host_only)
  if overrides and not parser.epilog:
    parser.epilog = OVERRIDES_HELP


def _host_only() -> None:
  """Keep JAX off accelerators (``JAX_PLATFORMS=cpu``) before any backend starts: a command that
  does CPU work must not take a GPU's memory from a training job beside it."""
  import os
  os.environ["JAX_PLATFORMS"] = "cpu"
  jax.config.update("jax_platforms", "cpu")


def _maybe_initialize_distributed(args) -> None:
  """``jax.distributed.initialize`` when several processes take part (flags, SLURM or TPU pods)."""
  import os
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


def cmd_train(args, extra) -> int:
  """Train a world model in WORKDIR, resuming from its latest checkpoint if it has one."""
  from wmjax.train.loop import train
  _maybe_initialize_distributed(args)
  config = _config_from_args(args, extra)
  allow = [k for item in args.allow_config_change for k in item.split(",") if k.strip()]
  _, result = train(config, args.workdir, allow_config_change=allow)
  if jax.process_index() == 0:
    print(json.dumps(result, indent=2))
  # stopped by a signal before the end: the conventional 128 + signal (143 SIGTERM, 130 SIGINT)
  return 128 + result["signal"] if "signal" in result else 0


def cmd_evaluate(args, extra) -> int:
  """Evaluate a checkpoint on a held-out split: IRASim short / long trajectories and the WPE
  context-horizon sweep, model against the copy-last-frame baseline. Writes metrics.json,
  report.md and per-trajectory videos (ground truth | prediction | difference)."""
  from wmjax.eval.evaluate import evaluate_checkpoint
  out, results = evaluate_checkpoint(
      args.workdir, split=args.split, out=args.out, protocols=args.protocols.split(","),
      step=args.step, params=args.params, batch_size=args.batch_size,
      max_trajectories=args.max_trajectories, videos=args.videos, num_sets=args.sets,
      sweep_frames=args.sweep_frames, seed=args.seed, mask_key=args.mask_key,
      frame_features=args.frame_features, clip_features=args.clip_features,
      overrides=_overrides(extra), param_dtype=args.param_dtype)
  with open(f"{out}/report.md") as f:
    print(f.read())
  print(f"wrote {out}/metrics.json, report.md and videos/")
  return 0


def cmd_rollout(args, extra) -> int:
  """Roll a trained model out from your own start frame(s) under your own raw action sequence
  (normalised with the checkpoint's statistics); writes rollout.mp4, rollout.gif, grid.png and
  frames.npy (uint8 [B, c+N, H, W, 3])."""
  import os

  from wmjax.eval import inputs
  from wmjax.eval import video as video_lib
  from wmjax.frames import to_model
  from wmjax.frames import to_uint8
  from wmjax.model import load_model
  from wmjax.rollout import rollout

  model = load_model(args.workdir, step=args.step, params=args.params,
                     overrides=_overrides(extra), param_dtype=args.param_dtype)
  config = model.config
  frames = inputs.read_frames(args.frames, model.image_shape, resize=args.resize,
                              value_range=args.frame_range)
  actions = inputs.read_actions(args.actions, model.action_stats.action_dim)
  stats = model.action_stats
  if not args.allow_extrapolation:
    low, high = stats.min, stats.max
    if args.normalized:
      mode = config.data.normalization
      low, high = stats.normalize(low[None], mode)[0], stats.normalize(high[None], mode)[0]
    inputs.check_action_range(actions, low, high, args.actions)
  if len(frames) != len(actions):
    raise SystemExit(f"wmjax rollout: {len(frames)} start-frame sets but {len(actions)} action "
                     f"sequences")
  actions = stats.normalize(actions, "none" if args.normalized else config.data.normalization,
                            pad_to=config.model.action_dim)
  c = frames.shape[1]
  room = config.model.num_frames - c
  if room < 1:
    raise SystemExit(f"wmjax rollout: {c} context frames leave no room in the model's "
                     f"{config.model.num_frames}-frame window")
  if args.horizon is not None and not 1 <= args.horizon <= room:
    raise SystemExit(f"wmjax rollout: --horizon must be between 1 and {room} (the model's "
                     f"{config.model.num_frames}-frame window less {c} context frame(s)), got "
                     f"{args.horizon}")
  horizon = args.horizon or min(config.rollout.horizon, room)
  encode_key, rollout_key = jax.random.split(jax.random.key(args.seed))
  context = model.codec.encode(to_model(frames), encode_key)
  decoded = np.asarray(model.codec.decode(rollout(model.world_model, model.params, context,
                                                  actions, rollout_key, horizon=horizon)))
  if not np.isfinite(decoded).all():
    raise SystemExit("wmjax rollout: the model produced NaN / inf frames from these inputs; "
                     "nothing was written")
  out = to_uint8(decoded)
  os.makedirs(args.out, exist_ok=True)
  np.save(os.path.join(args.out, "frames.npy"), out)
  video = video_lib.stack_rows(list(out))
  for name in ("rollout.mp4", "rollout.gif"):
    video_lib.write_video(os.path.join(args.out, name), video, fps=args.fps)
  video_lib.write_png(os.path.join(args.out, "grid.png"), video_lib.frame_grid(list(out)))
  print(f"{out.shape[0]} rollout(s) of {c} context + {out.shape[1] - c} frames (horizon "
        f"{horizon}, checkpoint step {model.step}) -> {args.out}")
  return 0


def _load_for_simulator(args, extra):
  from wmjax.model import load_model
  return load_model(args.workdir, step=args.step, params=args.params, overrides=_overrides(extra))


def cmd_eval_policy(args, extra) -> int:
  """Evaluate policies in the world model and, for ground truth, in the simulator (gym-pusht)
  from the same initial states: Monte Carlo values (mean ± stderr), Pearson / Spearman / Kendall,
  rank agreement, MMRV, value gap; writes policy_eval.json, policy_eval.md and one video per
  policy (simulator | world model | difference)."""
  from wmjax.eval.rewards import reward_from_spec
  from wmjax.tasks.pusht import simulator as pusht
  from wmjax.tasks.pusht.evaluate import evaluate_policies, policy_report
  model = _load_for_simulator(args, extra)
  chunk = model.config.rollout.horizon
  specs = args.policy or ["push", "push:0.1", "push:0.2", "push:0.5", "stay"]
  policies = {spec.replace(":", "@"): pusht.policy_from_spec(spec, chunk) for spec in specs}
  out = args.out or f"{args.workdir}/policy_eval"
  rewards = {spec: reward_from_spec(spec) for spec in args.reward or ["coverage"]}
  result = evaluate_policies(model, policies, rewards, episodes=args.episodes, steps=args.steps,
                             seed=args.seed, scan=args.scan, out=out, videos=args.videos)
  print(policy_report(result))
  print(f"wrote {out}/policy_eval.json, policy_eval.md and videos/")
  return 0


def cmd_plan(args, extra) -> int:
  """Model-predictive control by ranking in the simulator (gym-pusht): at each replanning, K
  chunks from the proposal policy are imagined in one batch, scored by the value function, and
  the best one's first actions are executed; final simulator coverage for each K."""
  from wmjax.eval.planning import policy_proposal
  from wmjax.eval.rewards import reward_from_spec
  from wmjax.tasks.pusht import simulator as pusht
  from wmjax.tasks.pusht.evaluate import plan_in_simulator
  model = _load_for_simulator(args, extra)
  length = args.plan_length or model.config.rollout.horizon
  proposal = policy_proposal(pusht.policy_from_spec(args.proposal, length))
  out = args.out or f"{args.workdir}/plan"
  candidates = [int(k) for k in args.candidates.split(",")]
  result = plan_in_simulator(model, proposal, reward_from_spec(args.value), candidates,
                             episodes=args.episodes, steps=args.steps, seed=args.seed,
                             execute=args.execute, lookahead=args.lookahead, out=out)
  print(result["table"])
  print(f"wrote {out}/plan.json and plan.md")
  return 0


def cmd_launch(args, extra) -> int:
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


def cmd_info(args, extra) -> int:
  """Parameter count, forward FLOPs, sampling cost and a per-device training-memory estimate of a
  config, without allocating the model."""
  from wmjax.model import WorldModel
  from wmjax.nn import forward_flops
  from wmjax.rollout import block_flops

  config = _config_from_args(args, extra)
  wm = WorldModel.from_config(config)
  net = wm.network
  h, w, c = config.frame_shape
  frames = config.rollout.context + config.rollout.horizon
  shapes = jax.eval_shape(lambda: wm.init(jax.random.key(0), (h, w, c), frames=frames))
  params = sum(int(np.prod(p.shape)) for p in jax.tree.leaves(shapes))
  flops = forward_flops(net, 1, frames, h, w)
  calls = wm.sampler.model_calls(config.rollout.horizon)
  guidance = 2 if wm.guided else 1
  sampling_flops = block_flops(wm, 1, config.rollout.context, config.rollout.horizon, h, w)
  info = {
      "name": config.name or args.config,
      "parameters": params,
      "parameter_bytes_fp32": 4 * params,
      "frame_shape": [h, w, c],
      "window_frames": frames,
      "forward_gflop_per_window": flops / 1e9,
      "model_calls_per_block": calls * guidance,
      "kv_cache": wm.sampler.kv_cache,
      "gflop_per_generated_frame": sampling_flops / config.rollout.horizon / 1e9,
  }
  if "batch_size" in config and "mesh" in config:
    from wmjax.train import memory
    info["train_memory_per_device"] = memory.estimate(config, args.devices)
  print(json.dumps(info, indent=2))
  return 0


def cmd_compile(args, extra) -> int:
  """Compile the exact sharded train step (or one jitted rollout block) of a config for a target,
  without its hardware, and print per-device memory from XLA (arguments, outputs, temporaries,
  total), the device's memory and whether it fits, the mesh, XLA's and the analytic FLOPs and the
  compile time. When a train step does not fit, also the setting train.auto_fit would choose
  (remat none -> dots -> full, then gradient-accumulation micro-batches). Targets: h100[:N],
  h200[:N], a100[:N] (needs JAX's CUDA plugin, no GPU), TPU topologies such as v5p:2x2x1,
  v5p:4x4x4, v5e:4x4, v6e:2x2 (needs libtpu, no TPU) and cpu:N. GPU memory counts
  XLA_PYTHON_CLIENT_MEM_FRACTION (default 0.75) of the card. Exits 1 when the config's own
  setting does not fit."""
  from wmjax.train import fit
  name, _, count = args.target.partition(":")
  if name == "cpu" and count.isdigit():
    jax.config.update("jax_num_cpu_devices", int(count))
  config = _config_from_args(args, extra)
  try:
    target = fit.parse_target(args.target)
  except ValueError as e:
    raise SystemExit(f"wmjax compile: {e}") from e
  budget = None if args.budget_gib is None else int(args.budget_gib * fit.GIB)
  if args.what == "rollout":
    report = fit.compile_rollout(config, target, args.batch, budget)
  else:
    first = fit.compile_step(config, target, args.batch, budget)
    report = first[2]
    if report["fits"] is False:
      _, _, chosen = fit.fit_step(config, target, budget, args.batch, first=first,
                                  log=lambda line: print(line, flush=True))
      report["auto_fit"] = {"remat": chosen["remat"], "grad_accum": chosen["grad_accum"],
                            "total_gib": chosen["total_gib"], "tried": chosen["tried"]}
  print(fit.describe(report))
  if "auto_fit" in report:
    choice = report["auto_fit"]
    print(f"auto_fit would choose model.remat={choice['remat']!r} "
          f"optim.grad_accum={choice['grad_accum']} ({choice['total_gib']:.3g} GiB per device)")
  print(json.dumps(report, indent=2))
  if args.out:
    with open(args.out, "w") as f:
      json.dump(report, f, indent=2)
  return 1 if report["fits"] is False else 0


def cmd_data_prepare(args, extra) -> int:
  """Generate a dataset (gridworld, or Push-T from the gym-pusht simulator) as an RLDS TFDS
  dataset in ArrayRecord, once per parameter set; prints the builder directory."""
  del extra
  from wmjax.data.sources import GENERATED
  params_class, prepare = GENERATED[args.dataset]
  fields = {f.name: getattr(args, f.name) for f in dataclasses.fields(params_class)}
  print(prepare(args.data_dir, params_class(**fields)))
  return 0


def cmd_data_convert(args, extra) -> int:
  """Rewrite a TFRecord RLDS dataset (TFDS builder directory) as ArrayRecord."""
  del extra
  from wmjax.data.convert import convert_to_array_record
  print(convert_to_array_record(args.src, args.dst))
  return 0


def cmd_data_stats(args, extra) -> int:
  """Compute (or show the cached) action statistics of a dataset split (cached per split and
  spec: those of train[:95%] are of exactly those episodes)."""
  del extra
  from wmjax.data.sources import action_stats
  stats = action_stats(args.builder_dir, args.split, args.name, recompute=args.recompute)
  print(json.dumps(dict(stats.to_dict(), split=args.split), indent=2))
  return 0


def cmd_data_inspect(args, extra) -> int:
  """Print a prepared TFDS dataset's splits and features, and a suggested dataset spec
  (config.data.spec) to train on it with no code."""
  del extra
  from wmjax.data.describe import describe
  from wmjax.data.sources import open_builder
  print(describe(open_builder(args.builder_dir)))
  return 0


def cmd_data_import(args, extra) -> int:
  """Import a local LeRobot dataset (meta/info.json, data/**/*.parquet, videos/**/*.mp4; v2.x or
  v3 layout) as an RLDS dataset in ArrayRecord; prints the builder directory. Train on it with
  configs/rlds.py and --config.data.builder_dir=OUT."""
  del extra
  from wmjax.data.lerobot import import_lerobot
  print(import_lerobot(args.src, args.out, camera=args.camera))
  return 0


def cmd_data_encode(args, extra) -> int:
  """Encode a dataset's episodes with the config's codec into ArrayRecord latents (IRASim's
  pre-encoding); train from them with --config.data.latents_dir=OUT."""
  import itertools

  from wmjax.codecs import make_codec
  from wmjax.data.latents import codec_description, encode_dataset
  from wmjax.data.sources import member_configs, open_dataset
  from wmjax.frames import to_model

  config = _config_from_args(args, extra)
  members = {m.dataset: m for m in member_configs(config.data)}
  if args.dataset is None and len(members) > 1:
    raise SystemExit(f"wmjax data encode: the config mixes {sorted(members)}; pick one with "
                     f"--dataset")
  if args.dataset is not None and args.dataset not in members:
    raise SystemExit(f"wmjax data encode: --dataset {args.dataset!r} is not in the config's data "
                     f"({sorted(members)})")
  data = members[args.dataset] if args.dataset else next(iter(members.values()))
  codec = make_codec(config.codec)
  dataset = open_dataset(data)
  splits = args.splits.split(",") if args.splits else [data.train_split, data.eval_split]
  resolution = dataset.resolution(dataset.split(splits[0]).spec)
  stats = dataset.train_stats()
  keys = (jax.random.fold_in(jax.random.key(args.seed), i) for i in itertools.count())
  out = encode_dataset(dataset.builder_dir, args.out, splits, dataset.specs, resolution,
                       lambda frames: np.asarray(codec.encode(to_model(frames), next(keys))),
                       codec_description(config.codec), stats.to_dict())
  print(out)
  return 0


def _float_tuple(text: str) -> tuple[float, ...]:
  return tuple(float(part) for part in text.split(",") if part.strip())


def _bool(text: str) -> bool:
  value = text.strip().lower()
  if value not in ("true", "false", "1", "0"):
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")
  return value in ("true", "1")


def _add_data_commands(sub) -> None:
  from wmjax import tasks  # noqa: F401  (importing it registers the generated datasets)
  from wmjax.data.sources import GENERATED
  data = sub.add_parser("data", help="prepare, convert and summarise datasets")
  data_sub = data.add_subparsers(dest="data_command", required=True)

  prepare = data_sub.add_parser("prepare", help="generate a dataset (RLDS, ArrayRecord)",
                                description=cmd_data_prepare.__doc__)
  prepare_sub = prepare.add_subparsers(dest="dataset", required=True)
  for name, (params_class, _) in GENERATED.items():
    dataset = prepare_sub.add_parser(name, help=f"generate the {name} dataset",
                                     description=cmd_data_prepare.__doc__)
    dataset.add_argument("--data_dir", required=True, help="TFDS data directory to write into")
    for field in dataclasses.fields(params_class):
      parse = (_float_tuple if isinstance(field.default, tuple) else
               _bool if isinstance(field.default, bool) else type(field.default))
      shown = ",".join(map(str, field.default)) if isinstance(field.default, tuple) else field.default
      dataset.add_argument(f"--{field.name}", type=parse, default=field.default,
                           help=f"{name} {field.name} (default {shown})")
    _register(dataset, cmd_data_prepare, host_only=True)

  convert = data_sub.add_parser("convert", help="TFRecord RLDS -> ArrayRecord (no beam)",
                                description=cmd_data_convert.__doc__)
  convert.add_argument("src", help="builder directory, e.g. gs://gresearch/robotics/bridge/0.1.0")
  convert.add_argument("dst", help="output builder directory (must not exist)")
  _register(convert, cmd_data_convert, host_only=True)

  encode = data_sub.add_parser("encode", help="pre-encode a dataset with the config's codec",
                               description=cmd_data_encode.__doc__)
  encode.add_argument("--config", required=True, help="config file, optionally file.py:arg")
  encode.add_argument("--out", required=True, help="output directory (must not exist)")
  encode.add_argument("--splits", default=None,
                      help="comma-separated splits (default: the config's train and eval splits)")
  encode.add_argument("--dataset", default=None, help="the mixture member to encode")
  encode.add_argument("--seed", type=int, default=0, help="for codecs that sample latents")
  _register(encode, cmd_data_encode, overrides=True)

  stats = data_sub.add_parser("stats", help="action statistics, cached as JSON beside the data",
                              description=cmd_data_stats.__doc__)
  stats.add_argument("builder_dir")
  stats.add_argument("--split", default="train")
  stats.add_argument("--name", default=None, help="dataset spec name (default: the builder's)")
  stats.add_argument("--recompute", action="store_true")
  _register(stats, cmd_data_stats, host_only=True)

  inspect = data_sub.add_parser("inspect", help="features of a TFDS dataset and a suggested spec",
                                description=cmd_data_inspect.__doc__)
  inspect.add_argument("builder_dir")
  _register(inspect, cmd_data_inspect, host_only=True)

  import_ = data_sub.add_parser("import", help="bring another format in as RLDS (ArrayRecord)",
                                description=cmd_data_import.__doc__)
  import_sub = import_.add_subparsers(dest="format", required=True)
  lerobot = import_sub.add_parser("lerobot", help="a local LeRobot dataset (v2.x or v3)",
                                  description=cmd_data_import.__doc__)
  lerobot.add_argument("src", help="LeRobot dataset directory (with meta/info.json)")
  lerobot.add_argument("out", help="output builder directory (must not exist)")
  lerobot.add_argument("--camera", default=None,
                       help="camera feature stored as observation/image, e.g. "
                            "observation.images.top (default: the first); every camera is also "
                            "kept as observation/<name>")
  _register(lerobot, cmd_data_import, host_only=True)


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(
      prog="wmjax", description="Action-conditioned video world models for robot manipulation.")
  sub = parser.add_subparsers(dest="command", required=True)
  train = sub.add_parser("train", help="train (or resume) a world model in a workdir",
                         description=cmd_train.__doc__)
  train.add_argument("--config", required=True, help="config file, optionally file.py:arg")
  train.add_argument("--workdir", required=True, help="checkpoints, logs, videos and metrics")
  train.add_argument("--coordinator_address", default=None,
                     help="host:port of process 0, for a multi-process run started by hand")
  train.add_argument("--num_processes", type=int, default=None)
  train.add_argument("--process_id", type=int, default=None)
  train.add_argument("--allow_config_change", action="append", default=[], metavar="KEY[,KEY]",
                     help="on resume, accept these changed config keys (or whole sections, e.g. "
                          "optim); repeatable")
  _register(train, cmd_train, overrides=True)
  from wmjax.train.resume import SAFE_ON_RESUME
  train.epilog = OVERRIDES_HELP + " " + RESUME_HELP.format(safe=", ".join(SAFE_ON_RESUME))

  evaluate = sub.add_parser("evaluate", help="IRASim / WPE evaluation of a checkpoint",
                            description=cmd_evaluate.__doc__)
  evaluate.add_argument("--workdir", required=True, help="training workdir with checkpoints/")
  evaluate.add_argument("--split", default="test", help="split of the training dataset")
  evaluate.add_argument("--protocols", default="short,long,sweep",
                        help="comma-separated: short, long (IRASim), sweep (WPE c/h sweep)")
  evaluate.add_argument("--out", default=None, help="default WORKDIR/eval/SPLIT-stepN")
  evaluate.add_argument("--step", type=int, default=None, help="checkpoint (default: latest)")
  evaluate.add_argument("--params", choices=["ema", "raw"], default="ema")
  evaluate.add_argument("--param_dtype", choices=["float32", "bfloat16"], default="float32",
                        help="parameters' dtype for inference (compute: --config.model.dtype)")
  evaluate.add_argument("--batch_size", type=int, default=16, help="rollouts at once")
  evaluate.add_argument("--max_trajectories", type=int, default=None,
                        help="cap per protocol (default: all)")
  evaluate.add_argument("--videos", type=int, default=4, help="videos written per protocol")
  evaluate.add_argument("--sets", type=int, default=4, help="generations per sweep setting")
  evaluate.add_argument("--sweep_frames", type=int, default=None,
                        help="target frames of the sweep (default 2 x rollout.horizon)")
  evaluate.add_argument("--seed", type=int, default=0)
  evaluate.add_argument("--mask_key", default=None,
                        help="per-step dataset feature holding arm / object masks (masked MSE)")
  evaluate.add_argument("--frame_features", default=None, metavar="MODULE:FUNCTION",
                        help="FID features: frames [N, H, W, 3] in [0, 1] -> [N, D]")
  evaluate.add_argument("--clip_features", default=None, metavar="MODULE:FUNCTION",
                        help="FVD features: clips [N, T, H, W, 3] in [0, 1] -> [N, D]")
  _register(evaluate, cmd_evaluate, overrides=True)

  roll = sub.add_parser("rollout", help="roll a checkpoint out from your frames and actions",
                        description=cmd_rollout.__doc__)
  roll.add_argument("--workdir", required=True, help="training workdir with checkpoints/")
  roll.add_argument("--frames", required=True, nargs="+",
                    help="context frames: image files (in order) or one .npy [c, H, W, 3]")
  roll.add_argument("--actions", required=True, help=".npy [N, A] / [B, N, A] or .csv (N x A)")
  roll.add_argument("--out", required=True, help="output directory")
  roll.add_argument("--step", type=int, default=None, help="checkpoint (default: latest)")
  roll.add_argument("--params", choices=["ema", "raw"], default="ema")
  roll.add_argument("--param_dtype", choices=["float32", "bfloat16"], default="float32",
                    help="parameters' dtype for inference (compute: --config.model.dtype)")
  roll.add_argument("--horizon", type=int, default=None,
                    help="frames per block (default: the config's, fitted to the window)")
  roll.add_argument("--seed", type=int, default=0)
  roll.add_argument("--fps", type=float, default=4.0)
  roll.add_argument("--resize", action="store_true", help="resize frames to the model's size")
  roll.add_argument("--normalized", action="store_true",
                    help="the actions are already normalised (skip the checkpoint statistics)")
  roll.add_argument("--frame_range", choices=["-1,1", "0,1"], default=None,
                    help="value range of float .npy frames (needed when they are all >= 0)")
  roll.add_argument("--allow_extrapolation", action="store_true",
                    help="roll out actions far outside the training range (refused otherwise)")
  _register(roll, cmd_rollout, overrides=True)

  def simulator_args(parser, default_out):
    parser.add_argument("--workdir", required=True, help="training workdir with checkpoints/")
    parser.add_argument("--simulator", default="pusht", choices=["pusht"],
                        help="ground-truth simulator the initial states and real steps come from")
    parser.add_argument("--episodes", type=int, default=32,
                        help="episodes, i.e. initial states (default 32)")
    parser.add_argument("--steps", type=int, default=24,
                        help="control steps per episode (default 24)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--step", type=int, default=None, help="checkpoint step (latest)")
    parser.add_argument("--params", default="ema", choices=["ema", "raw"])
    parser.add_argument("--out", default=None, help=f"output directory (WORKDIR/{default_out})")

  overrides_note = ("Inference settings of the checkpoint's config can be overridden, e.g. "
                    "--config.sampling.num_steps=4.")
  policy = sub.add_parser("eval-policy", help="policy values in the world model vs the simulator",
                          description=cmd_eval_policy.__doc__, epilog=overrides_note)
  simulator_args(policy, "policy_eval")
  policy.add_argument("--policy", action="append",
                      help="push | push:NOISE | stay | module:attribute, repeatable (default: "
                           "push, push:0.1, push:0.2, push:0.5, stay)")
  policy.add_argument("--reward", action="append",
                      help="coverage | vlm | classifier:DIR | goal:IMAGE, repeatable, all scored "
                           "on the same rollouts (default: coverage)")
  policy.add_argument("--scan", action="store_true",
                      help="roll out inside one jitted scan (pure-JAX policies)")
  policy.add_argument("--videos", type=int, default=4, help="episodes per policy video")
  _register(policy, cmd_eval_policy, overrides=True)

  plan = sub.add_parser("plan", help="model-predictive control by ranking, run in the simulator",
                        description=cmd_plan.__doc__, epilog=overrides_note)
  simulator_args(plan, "plan")
  plan.add_argument("--candidates", default="1,5,10,50",
                    help="comma-separated K values (default 1,5,10,50)")
  plan.add_argument("--proposal", default="push:0.2",
                    help="proposal policy: push:NOISE | stay | module:attribute (default "
                         "push:0.2)")
  plan.add_argument("--plan_length", type=int, default=None,
                    help="actions per candidate (default: the model's rollout horizon)")
  plan.add_argument("--execute", type=int, default=None,
                    help="actions executed before replanning (default: the rollout horizon)")
  plan.add_argument("--value", default="coverage",
                    help="value function on imagined frames: coverage | vlm | classifier:DIR | "
                         "goal:IMAGE (default coverage)")
  plan.add_argument("--lookahead", action="store_true",
                    help="also plan with the simulator itself as the model (a reference)")
  _register(plan, cmd_plan, overrides=True)

  launch = sub.add_parser("launch", help="run a command as N local processes (jax.distributed)",
                          description=cmd_launch.__doc__)
  launch.add_argument("--num_processes", type=int, required=True)
  launch.add_argument("--platform", choices=["cpu", "gpu"], default="cpu")
  launch.add_argument("--devices_per_process", type=int, default=1,
                      help="simulated CPU devices, or GPUs, per process")
  launch.add_argument("--port", type=int, default=None, help="coordinator port (default: free)")
  launch.add_argument("command", nargs=argparse.REMAINDER,
                      help="-- followed by the wmjax command, e.g. -- train --config F ...")
  _register(launch, cmd_launch)

  info = sub.add_parser("info", help="parameter count and FLOPs of a config (no allocation)",
                        description=cmd_info.__doc__)
  info.add_argument("--config", required=True, help="config file, optionally file.py:arg")
  info.add_argument("--devices", type=int, default=None,
                    help="devices to estimate training memory for (default: this machine's)")
  _register(info, cmd_info, overrides=True, host_only=True)

  compile_ = sub.add_parser("compile", help="compile a train step or rollout for a device target "
                                            "(no hardware needed): memory, fits, FLOPs",
                            description=cmd_compile.__doc__)
  compile_.add_argument("--config", required=True, help="config file, optionally file.py:arg")
  compile_.add_argument("--target", required=True,
                        help="h100[:N] | h200[:N] | a100[:N] | TPU topology (v5p:2x2x1, v5e:4x4, "
                             "...) | cpu:N")
  compile_.add_argument("--what", choices=["train", "rollout"], default="train",
                        help="the train step (default) or one rollout block")
  compile_.add_argument("--batch", type=int, default=None,
                        help="global batch (default: the config's batch_size; rollout: 8)")
  compile_.add_argument("--budget_gib", type=float, default=None,
                        help="memory per device to fit (default: the target's usable memory)")
  compile_.add_argument("--out", default=None, help="also write the report as JSON here")
  _register(compile_, cmd_compile, overrides=True, host_only=True)
  _add_data_commands(sub)
  args, extra = parser.parse_known_args(argv)
  if args.func is not cmd_launch:  # launch passes the rest on to its command
    bad = [a for a in extra if not (args.takes_overrides and a.startswith("--config."))]
    bad += [a for a in extra if a.startswith("--config.") and "=" not in a]
    if bad:
      args.command_parser.error(
          f"unrecognized arguments: {' '.join(bad)}"
          + ("; config overrides look like --config.KEY=VALUE" if args.takes_overrides else ""))
  if args.host_only:
    _host_only()
  from wmjax.config import ConfigError
  from wmjax.errors import RunError
  try:
    return args.func(args, extra)
  except (ConfigError, RunError) as e:
    # a condition the message explains, with the way out: no traceback
    print(f"{args.command_parser.prog}: {e}", file=sys.stderr)
    return 2 if isinstance(e, ConfigError) else 1


if __name__ == "__main__":
  sys.exit(main())
