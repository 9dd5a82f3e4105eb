"""``wmjax import``: another codebase's checkpoint as a wmjax workdir."""

from __future__ import annotations

from wmjax.cli import common


def import_irasim(args, extra) -> int:
  """Convert an IRASim checkpoint (a PyTorch .pt of bytedance/IRASim's models/irasim.py) into a
  new workdir that evaluate, rollout and load_model read like a training workdir. The size and
  the variant come from the weights, the dataset from the path (IRASim's release layout
  DATASET/checkpoints/VARIANT/STEP.pt) unless named. The .pt file is read without PyTorch, and
  nothing it names runs."""
  from wmjax.checkpoints import irasim

  config = irasim.import_checkpoint(args.checkpoint, args.workdir, dataset=args.dataset,
                                    variant=args.variant, weights=args.weights,
                                    config_path=args.config or irasim.DEFAULT_CONFIG,
                                    final_frame_ada=args.final_frame_ada)
  print(f"{args.checkpoint} ({args.weights} weights) -> {args.workdir}: {config.name}")
  if config.model.cond == "frame":  # Frame-Ada
    print("Frame-Ada's final layer sees the actions" if args.final_frame_ada else
          "Frame-Ada's final layer sees the timestep only, as in IRASim's published checkpoints; "
          "one trained with IRASim's final_frame_ada=True needs --final_frame_ada (the weights "
          "do not tell)")
  return 0


def add_parser(sub) -> None:
  """The ``import`` command group."""
  parser = sub.add_parser("import", help="another codebase's checkpoint as a wmjax workdir")
  import_sub = parser.add_subparsers(dest="format", required=True)
  irasim = import_sub.add_parser("irasim", help="an IRASim checkpoint (.pt)",
                                 description=import_irasim.__doc__)
  irasim.add_argument("checkpoint", help="IRASim .pt file ({'model', 'ema', 'opt', 'args'} or a state dict)")
  irasim.add_argument("--workdir", required=True, help="new (or empty) directory to write")
  irasim.add_argument("--dataset", default=None, metavar="{rt1,bridge}",
                      help="the dataset it was trained on (default: from the path; "
                           "Language-Table models are refused, with the reason)")
  irasim.add_argument("--variant", choices=["frame_ada", "video_ada"], default=None,
                      help="default: from the weights")
  irasim.add_argument("--weights", choices=["ema", "model"], default="ema",
                      help="which state dict of the file (default: the EMA)")
  irasim.add_argument("--final_frame_ada", action="store_true",
                      help="Frame-Ada: the final layer sees the actions too (IRASim's "
                           "final_frame_ada=True; its published checkpoints are without)")
  irasim.add_argument("--config", default=None,
                      help="configs/irasim.py of a wmjax checkout (default: this checkout's)")
  common.register(irasim, import_irasim, host_only=True)
