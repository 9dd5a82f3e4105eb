"""``wmjax evaluate``: the IRASim / WPE evaluation of a checkpoint on a held-out split."""

from __future__ import annotations

from wmjax.cli import common


def run(args, extra) -> int:
  """Evaluate a checkpoint on a held-out split: IRASim short / long trajectories and the WPE
  context-horizon sweep, model against the copy-last-frame baseline. Writes metrics.json,
  report.md and per-trajectory videos (ground truth | prediction | difference)."""
  from wmjax.eval.evaluate import evaluate_checkpoint
  out, _ = evaluate_checkpoint(
      args.workdir, split=args.split, out=args.out, protocols=args.protocols.split(","),
      step=args.step, params=args.params, batch_size=args.batch_size,
      max_trajectories=args.max_trajectories, videos=args.videos, num_sets=args.sets,
      sweep_frames=args.sweep_frames, seed=args.seed, mask_key=args.mask_key,
      frame_features=args.frame_features, clip_features=args.clip_features,
      overrides=common.overrides(extra), param_dtype=args.param_dtype)
  with open(f"{out}/report.md") as f:
    print(f.read())
  print(f"wrote {out}/metrics.json, report.md and videos/")
  return 0


def add_parser(sub) -> None:
  """The ``evaluate`` command."""
  parser = sub.add_parser("evaluate", help="IRASim / WPE evaluation of a checkpoint",
                          description=run.__doc__)
  parser.add_argument("--workdir", required=True, help=common.WORKDIR_HELP)
  parser.add_argument("--split", default=None,
                      help="split of the training dataset (default: the config's "
                           "data.eval_split)")
  parser.add_argument("--protocols", default="short,long,sweep",
                      help="comma-separated: short, long (IRASim), sweep (WPE c/h sweep)")
  parser.add_argument("--out", default=None, help="default WORKDIR/eval/SPLIT-stepN")
  common.checkpoint_args(parser)
  parser.add_argument("--batch_size", type=int, default=16, help="rollouts at once")
  parser.add_argument("--max_trajectories", type=int, default=None,
                      help="cap per protocol (default: all)")
  parser.add_argument("--videos", type=int, default=4, help="videos written per protocol")
  parser.add_argument("--sets", type=int, default=4, help="generations per sweep setting")
  parser.add_argument("--sweep_frames", type=int, default=None,
                      help="target frames of the sweep (default 2 x rollout.horizon)")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--mask_key", default=None,
                      help="per-step dataset feature holding arm / object masks (masked MSE)")
  parser.add_argument("--frame_features", default=None, metavar="MODULE:FUNCTION",
                      help="FID features: frames [N, H, W, 3] in [0, 1] -> [N, D]")
  parser.add_argument("--clip_features", default=None, metavar="MODULE:FUNCTION",
                      help="FVD features: clips [N, T, H, W, 3] in [0, 1] -> [N, D]")
  common.register(parser, run, takes_overrides=True)
