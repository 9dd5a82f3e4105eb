"""The probe's T IoU at the first generated frame, split by how far the simulator's T moves into
that frame: is the pushed T lost where a push moves it most?

Reads probe JSON files (``probe.py --out``, per-window values) and the probe's reference windows
(``--data_dir``, as ``probe.py`` prepares them), and prints, for each group of windows by the T's
move from the last context frame to the first generated one (its centre, in the simulator's
512-unit coordinates), the model's T IoU and copying the last context frame's.

    python experiments/pusht/motion_split.py --workdir W/model --data_dir REF P1.json [P2.json ...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import probe  # noqa: E402  (the probe's windows, read the same way)

GROUPS = ((0.0, 0.5, "still"), (0.5, 5.0, "nudged"), (5.0, float("inf"), "pushed"))


def first_frame_moves(trajectories) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Per window: the T centre's move (simulator units) and turn (degrees) from the last context
  frame into the first generated one, and copying the last context frame's T IoU there."""
  from wmjax.tasks.pusht.metrics import pusht_metrics
  state = trajectories.extras["state"].astype(np.float64)  # [W, T, 5]: agent xy, T xy, T angle
  c = probe.CONTEXT
  shift = np.linalg.norm(state[:, c, 2:4] - state[:, c - 1, 2:4], axis=1)
  turn = np.degrees(np.abs(np.angle(np.exp(1j * (state[:, c, 4] - state[:, c - 1, 4])))))
  frames = trajectories.frames
  copy = pusht_metrics(frames[:, c - 1:c], frames[:, c:c + 1], None)["block_iou"][:, 0]
  return shift, turn, copy


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", required=True, help="a model the probes ran on (its data "
                                                       "config names the reference windows)")
  parser.add_argument("--data_dir", required=True, help="the probe's reference data")
  parser.add_argument("probes", nargs="+", help="probe JSON files")
  args = parser.parse_args(argv)
  from wmjax.model import load_model
  model = load_model(args.workdir)
  _, trajectories = probe.reference_windows(model, args.data_dir,
                                            probe.CONTEXT + probe.GENERATED)
  shift, turn, copy = first_frame_moves(trajectories)
  where = {(e, s): i for i, (e, s) in enumerate(zip(trajectories.episode, trajectories.start))}
  print("| probe | step | group | windows | T move, median (px at 48) | turn, median (deg) "
        "| model T IoU | copy T IoU |\n|---|---|---|---|---|---|---|---|")
  for path in args.probes:
    with open(path) as f:
      runs = json.load(f)
    name_of_file = os.path.join(*os.path.normpath(path).split(os.sep)[-2:])
    for run in runs if isinstance(runs, list) else [runs]:
      rows = np.asarray([where[(e, s)] for e, s in zip(run["episode"], run["start"])])
      iou = np.asarray(run["per_window"]["block_iou/step1"])
      for lo, hi, name in GROUPS:
        keep = (shift[rows] >= lo) & (shift[rows] < hi)
        if keep.any():
          print(f"| {name_of_file} | {run['step']} | {name} | {keep.sum()} | "
                f"{np.median(shift[rows][keep]) * 48 / 512:.2f} | "
                f"{np.median(turn[rows][keep]):.1f} | {iou[keep].mean():.3f} | "
                f"{copy[rows][keep].mean():.3f} |")
  return 0


if __name__ == "__main__":
  sys.exit(main())
