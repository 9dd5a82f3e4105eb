"""``wmjax rollout``: roll a checkpoint out from the user's own frames and actions."""

from __future__ import annotations

from wmjax.cli import common


def run(args, extra) -> int:
  """Roll a trained model out from your own start frame(s) under your own raw action sequence
  (normalised with the checkpoint's statistics); writes rollout.mp4, rollout.gif, grid.png and
  frames.npy (uint8 [B, c+N, H, W, 3])."""
  from wmjax.eval import inputs, user_rollout

  model = common.inference_model(args.workdir, args, extra)
  frames = inputs.read_frames(args.frames, model.image_shape, resize=args.resize,
                              value_range=args.frame_range)
  actions = inputs.read_actions(args.actions, model.action_stats.action_dim)
  actions = user_rollout.model_actions(model, actions, normalized=args.normalized,
                                       allow_extrapolation=args.allow_extrapolation,
                                       source=args.actions)
  context = frames.shape[1]
  try:
    horizon = user_rollout.rollout_horizon(model, context, args.horizon)
    out = user_rollout.roll_out(model, frames, actions, horizon, seed=args.seed)
  except ValueError as e:
    raise SystemExit(f"wmjax rollout: {e}") from e
  user_rollout.write_rollout(args.out, out, args.fps)
  print(f"{out.shape[0]} rollout(s) of {context} context + {out.shape[1] - context} frames "
        f"(horizon {horizon}, checkpoint step {model.step}) -> {args.out}")
  return 0


def add_parser(sub) -> None:
  """The ``rollout`` command."""
  parser = sub.add_parser("rollout", help="roll a checkpoint out from your frames and actions",
                          description=run.__doc__)
  parser.add_argument("--workdir", required=True, help=common.WORKDIR_HELP)
  parser.add_argument("--frames", required=True, nargs="+",
                      help="context frames: image files (in order) or one .npy [c, H, W, 3]")
  parser.add_argument("--actions", required=True,
                      help=".npy [N, A] / [B, N, A] or .csv (N x A)")
  parser.add_argument("--out", required=True, help="output directory")
  common.checkpoint_args(parser)
  parser.add_argument("--horizon", type=int, default=None,
                      help="frames per block (default: the config's, fitted to the window)")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--fps", type=float, default=4.0)
  parser.add_argument("--resize", action="store_true", help="resize frames to the model's size")
  parser.add_argument("--normalized", action="store_true",
                      help="the actions are already normalised (skip the checkpoint statistics)")
  parser.add_argument("--frame_range", choices=["-1,1", "0,1"], default=None,
                      help="value range of float .npy frames (needed when they are all >= 0)")
  parser.add_argument("--allow_extrapolation", action="store_true",
                      help="roll out actions far outside the training range (refused otherwise)")
  common.register(parser, run, takes_overrides=True)
