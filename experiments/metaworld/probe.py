"""The cheapest signal first: the arm metrics of several MetaWorld models on the same held-out
windows, one knob apart (multi-view against tiled, a training seed, a checkpoint).

Each model continues test-split windows (their first ``context`` frames, the recorded actions) for
``--frames`` frames open loop; the reader scores every generated frame: the hand's pixel error in
the first view (the one-step-ahead error is the first frame's), the object's error and the gap
between the hand positions the two views show, with standard errors over windows, beside copying
the last context frame. Writes ``--out`` (JSON) and prints a table.

    python experiments/metaworld/probe.py --reader W/reader --out probe.json \\
        W/model@600 W-tiled/model@600
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np


def windows(builder_dir: str, length: int, offsets=(0, 10)):
  """Test-split windows of ``length`` frames from each offset of every episode: frames ``[N,
  length, S, V*S, 3]``, actions ``[N, length-1, 4]``, ee_px ``[N, length, 2]``, state ``[N,
  length, 6]``."""
  from wmjax.data.rlds import decode_image
  from wmjax.data.sources import ArrayRecordEpisodes
  source = ArrayRecordEpisodes(builder_dir, "test")
  out = {k: [] for k in ("frames", "actions", "ee_px", "state")}
  for index in range(len(source)):
    episode = source.episode(index)
    for first in offsets:
      if first + length > len(episode):
        continue
      span = slice(first, first + length)
      out["frames"].append(np.stack([decode_image(im, None) for im in episode.images[span]]))
      out["actions"].append(episode.actions[first:first + length - 1])
      out["ee_px"].append(episode.extras["ee_px"][span])
      out["state"].append(episode.extras["state"][span])
  return {k: np.stack(v) for k, v in out.items()}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("models", nargs="+", help="training workdirs, WORKDIR@STEP for a checkpoint")
  parser.add_argument("--reader", required=True, help="the frame reader's directory")
  parser.add_argument("--frames", type=int, default=8, help="frames to imagine per window")
  parser.add_argument("--out", required=True, help="JSON file to write")
  args = parser.parse_args(argv)
  from wmjax.data.sources import dataset_dir
  from wmjax.model import load_model
  from wmjax.tasks.metaworld.evaluate import arm_metrics
  from wmjax.tasks.metaworld.reader import ArmReader
  reader = ArmReader.load(args.reader)
  results, data = {}, None
  for spec in args.models:
    workdir, _, step = spec.partition("@")
    model = load_model(workdir, step=int(step) if step else None)
    context = model.config.rollout.context
    if data is None:
      data = windows(dataset_dir(model.config.data), context + args.frames)
    result = arm_metrics(model, reader, data["frames"], data["actions"], data["ee_px"],
                         data["state"], out_png=os.path.splitext(args.out)[0]
                         + f"_{len(results)}.png")
    result["views"] = model.config.model.views
    result["step"] = model.step
    results[spec] = result
  results["windows"] = int(len(data["frames"]))
  with open(args.out, "w") as f:
    json.dump(results, f, indent=2)
  print(f"{results['windows']} held-out windows; hand pixel error (first view) after 1 / "
        f"{args.frames} imagined frames, mean ± s.e.; view gap (cm) after {args.frames}")
  for spec in args.models:
    r = results[spec]
    for name in ("model", "copy_last", "truth"):
      e, se = r[name]["ee_px_error"], r[name]["ee_px_error_stderr"]
      print(f"{spec:40s} {name:9s} {e[0]:.3f} ± {se[0]:.3f}   {e[-1]:.3f} ± {se[-1]:.3f}   "
            f"gap {r[name]['view_hand_gap_cm'][-1]:.2f}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
