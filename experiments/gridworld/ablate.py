"""Gridworld ablations: one training run per row, scored by the IRASim short and long protocols.

Each row trains ``configs/gridworld.py`` with the row's overrides (``wmjax train``), evaluates the
newest checkpoint on the held-out episodes (``wmjax evaluate --protocols short,long``) and saves
``results/NAME-seedS.json`` beside this file: the exact commands, the training wall time, and
mean ± standard error of the square error, square IoU, one-component fraction and PSNR of the
model and of copying the last frame. ``table`` prints the rows as Markdown.

    python experiments/gridworld/ablate.py run base --workdir_root /tmp/ablate
    python experiments/gridworld/ablate.py run mse --workdir_root /tmp/ablate \\
        --config.diffusion.kind=regression --config.diffusion.regime=irasim \\
        --config.sampling.sampler=euler --config.sampling.num_steps=1 \\
        --config.sampling.context_level=0.0
    python experiments/gridworld/ablate.py table
    python experiments/gridworld/ablate.py picture text_vs_raw.png EVAL_DIR_RAW EVAL_DIR_TEXT

``picture`` stacks the ground truth and the predictions of several evaluations of the same
held-out window (each evaluation's ``videos/VIDEO.png``: ground truth, prediction, difference).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import shlex
import subprocess
import sys
import time

import numpy as np
from PIL import Image

from wmjax.config import parse_args_with_overrides

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
METRICS = ("square_error_px", "square_iou", "square_one_component", "psnr")


def run_row(name: str, seed: int, overrides: list[str], workdir_root: str,
            config: str) -> dict:
  workdir = os.path.join(workdir_root, f"{name}-seed{seed}")
  train = ["wmjax", "train", "--config", config, "--workdir", workdir,
           f"--config.seed={seed}", *overrides]
  start = time.time()
  subprocess.run(train, check=True)
  return record(name, seed, overrides, workdir, train, time.time() - start)


def record(name: str, seed: int, overrides: list[str], workdir: str, train: list[str],
           train_s: float) -> dict:
  """Evaluate a trained workdir and save its row."""
  evaluate = ["wmjax", "evaluate", "--workdir", workdir, "--protocols", "short,long",
              "--videos", "4"]
  subprocess.run(evaluate, check=True)
  outs = sorted(glob.glob(os.path.join(workdir, "eval", "test-step*")), key=os.path.getmtime)
  with open(os.path.join(outs[-1], "metrics.json")) as f:
    results = json.load(f)
  row = {"name": name, "seed": seed, "overrides": overrides, "train_s": round(train_s, 1),
         "commands": [shlex.join(train), shlex.join(evaluate)], "eval_dir": outs[-1]}
  for protocol in ("short", "long"):
    for who in ("model", "copy_last"):
      for metric in METRICS:
        value = results[protocol][who].get(metric)
        if value is not None:
          row[f"{protocol}/{who}/{metric}"] = [value["mean"], value["stderr"]]
  os.makedirs(RESULTS, exist_ok=True)
  with open(os.path.join(RESULTS, f"{name}-seed{seed}.json"), "w") as f:
    json.dump(row, f, indent=1)
  return row


def _cell(value) -> str:
  if value is None:
    return "–"
  mean, stderr = value
  return f"{mean:.3g} ± {stderr:.2g}"


def table() -> str:
  rows = []
  for path in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
    with open(path) as f:
      rows.append(json.load(f))
  rows.sort(key=lambda r: os.path.getmtime(os.path.join(RESULTS, f"{r['name']}-seed{r['seed']}.json")))
  head = ("| row | seed | short error px | short IoU | short one-piece | long error px | long IoU "
          "| train s |")
  lines = [head, "|---" * 8 + "|"]
  for r in rows:
    cells = [r["name"], str(r["seed"])]
    for key in ("short/model/square_error_px", "short/model/square_iou",
                "short/model/square_one_component", "long/model/square_error_px",
                "long/model/square_iou"):
      cells.append(_cell(r.get(key)))
    cells.append(f"{r['train_s']:.0f}")
    lines.append("| " + " | ".join(cells) + " |")
  if rows:
    base = rows[0]
    lines.append("| copy last frame | | " + " | ".join(
        _cell(base.get(k)) for k in ("short/copy_last/square_error_px", "short/copy_last/square_iou",
                                     "short/copy_last/square_one_component",
                                     "long/copy_last/square_error_px",
                                     "long/copy_last/square_iou")) + " | |")
  lines += ["", "Overrides of each row (on `configs/gridworld.py`):", ""]
  lines += [f"- `{r['name']}`: `{' '.join(r['overrides']) or '(none)'}`" for r in rows
            if r["seed"] == min(x["seed"] for x in rows if x["name"] == r["name"])]
  return "\n".join(lines)


def grid_rows(image: np.ndarray) -> list[np.ndarray]:
  """The rows of a frame grid ``[H, W, 3]`` (:func:`wmjax.eval.video.frame_grid`): the bands
  between the all-white separator lines."""
  white = (image == 255).all(axis=(1, 2))
  rows, start = [], None
  for y, is_gap in enumerate(np.append(white, True)):
    if not is_gap and start is None:
      start = y
    elif is_gap and start is not None:
      rows.append(image[start:y])
      start = None
  return rows


def picture(out: str, eval_dirs: list[str], video: str) -> str:
  """Ground truth, then each evaluation's prediction of ``video``, one row each."""
  grids = [np.asarray(Image.open(os.path.join(d, "videos", f"{video}.png")).convert("RGB"))
           for d in eval_dirs]
  rows = [grid_rows(g) for g in grids]
  if any(len(r) != 3 for r in rows) or len({g.shape for g in grids}) != 1:
    raise ValueError(f"expected frame grids of 3 rows and one shape, got "
                     f"{[(len(r), g.shape) for r, g in zip(rows, grids)]}")
  if any(not np.array_equal(r[0], rows[0][0]) for r in rows):
    raise ValueError("the evaluations show different ground truths: not the same window")
  gap = np.full((grids[0].shape[0] - 3 * rows[0][0].shape[0]) // 2, 255, np.uint8)
  bands = [rows[0][0]] + [r[1] for r in rows]
  parts = [bands[0]]
  for band in bands[1:]:
    parts += [np.broadcast_to(gap[:, None, None], (len(gap),) + band.shape[1:]), band]
  Image.fromarray(np.concatenate(parts)).save(out)
  return out


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  sub = parser.add_subparsers(dest="command", required=True)
  run = sub.add_parser("run", help="train and evaluate one row")
  run.add_argument("name")
  run.add_argument("--seed", type=int, default=0)
  run.add_argument("--config", default="configs/gridworld.py")
  run.add_argument("--workdir_root", default="workdirs/gridworld_ablate")
  rec = sub.add_parser("record", help="evaluate a workdir trained elsewhere and save its row")
  rec.add_argument("name")
  rec.add_argument("--seed", type=int, default=0)
  rec.add_argument("--workdir", required=True)
  rec.add_argument("--train_command", required=True, help="the command that trained it")
  rec.add_argument("--train_s", type=float, required=True, help="its training wall time")
  sub.add_parser("table", help="print the rows as Markdown")
  pic = sub.add_parser("picture", help="ground truth over several evaluations' predictions")
  pic.add_argument("out", help="the PNG to write")
  pic.add_argument("eval_dirs", nargs="+", help="evaluation directories (EVAL/videos/VIDEO.png)")
  pic.add_argument("--video", default="short_000")
  # --config.KEY=VALUE overrides, as for `wmjax train` (for `record`: today's equivalent of its
  # config); an earlier `--` before them is still accepted
  args, args.overrides = parse_args_with_overrides(
      parser, [a for a in (sys.argv[1:] if argv is None else argv) if a != "--"])
  if args.overrides and args.command in ("table", "picture"):
    parser.error(f"{args.command} takes no overrides, got {args.overrides}")
  if args.command == "picture":
    print(picture(args.out, args.eval_dirs, args.video))
    return 0
  if args.command == "table":
    print(table())
    return 0
  if args.command == "record":
    row = record(args.name, args.seed, args.overrides, args.workdir, shlex.split(args.train_command),
                 args.train_s)
    print(json.dumps(row, indent=1))
    return 0
  row = run_row(args.name, args.seed, args.overrides, args.workdir_root, args.config)
  print(json.dumps(row, indent=1))
  return 0


if __name__ == "__main__":
  sys.exit(main())
