"""Push-T: the cheapest signals of a world model, on held-out windows of one reference dataset.

For each checkpoint step of a model, short open-loop rollouts from two true context frames under
the true actions of 10-frame windows (stride 10) of the reference dataset's ``test`` split (by
default today's data, all scripted pushes, whatever the model was trained on, so that models
trained on different data are scored on the same windows): per generated frame the T's IoU and
centroid error and the agent's centroid error (``wmjax.tasks.pusht.metrics``), for the model and
for copy-last-frame, over all windows and separately over the windows where the simulator's T
does not move (``still``: its pose changes by < 0.5 px and 0.5 deg over the window) and those
where it does (``moved``). A window's value is the mean of its frames at the given steps; means
and standard errors are over episodes (each episode's windows averaged first). Every window's
value is kept too (``per_window``, in the order of ``episode`` / ``start``), so that two models
can be compared window by window (:func:`paired`).

    python experiments/pusht/probe.py --workdir W/model --data_dir D --step 500 --step 1000 \\
        --out W/probe.json

Prints one table row per step and writes every number to ``--out``. ``--by_noise_level``
measures instead whether the model puts the agent back from one noisy frame, at each noise level
(:func:`by_noise_level`). ``--split_by_motion P.json`` (repeatable, no ``--step`` / ``--out``)
splits probes already written by how far the simulator's T moves into the first generated frame
(:func:`split_by_motion`): is the pushed T lost where a push moves it most?

    python experiments/pusht/probe.py --workdir W/model --data_dir D --split_by_motion P1.json \
        --split_by_motion P2.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

CONTEXT, GENERATED = 2, 8
LEVELS = (50, 200, 400, 600, 800, 999)  # --by_noise_level
# --split_by_motion: the T centre's move into the first generated frame, simulator units
MOTION_GROUPS = ((0.0, 0.5, "still"), (0.5, 5.0, "nudged"), (5.0, float("inf"), "pushed"))


def _episode_mean_se(values: np.ndarray, episodes: np.ndarray, keep: np.ndarray):
  """Mean and standard error over episodes of ``values [W]`` (windows ``keep``), each episode's
  windows averaged first; (nan, nan, 0) where no window is kept."""
  groups = [values[keep & (episodes == e)].mean() for e in np.unique(episodes[keep])]
  if not groups:
    return float("nan"), float("nan"), 0
  groups = np.asarray(groups)
  se = groups.std(ddof=1) / np.sqrt(len(groups)) if len(groups) > 1 else float("nan")
  return float(groups.mean()), float(se), len(groups)


def reference_windows(model, data_dir: str, frames: int, limit=None):
  """(``test``-split builder directory, ``Trajectories`` of its ``frames``-frame windows) of the
  reference dataset: the model's Push-T data without the random and idle agents (all scripted),
  prepared in ``data_dir`` if absent."""
  import functools

  from wmjax.data.sources import ArrayRecordEpisodes
  from wmjax.eval.trajectories import Trajectories, windows_of
  from wmjax.tasks.pusht import dataset as pusht_data

  params = dict(model.config.data.pusht)
  params.pop("mix", None)
  params.pop("random_reach", None)
  builder_dir = pusht_data.prepare(data_dir, pusht_data.PushTConfig.from_dict(params))
  normalize = functools.partial(model.action_stats.normalize,
                                mode=model.config.data.normalization,
                                pad_to=model.config.model.action_dim)
  windows = windows_of(ArrayRecordEpisodes(builder_dir, "test", "pusht"), frames,
                       tuple(model.image_shape[:2]), limit)
  return builder_dir, Trajectories.stack(windows, normalize)


def probe(workdir: str, step: int, data_dir: str, *, batch_size: int = 32, limit=None,
          picture: str | None = None, overrides: tuple[str, ...] = (), params: str = "ema") -> dict:
  import jax

  from wmjax.eval.rollouts import run_rollouts
  from wmjax.model import load_model
  from wmjax.registry import frame_metrics_of

  model = load_model(workdir, step=step, overrides=overrides, params=params)
  builder_dir, trajectories = reference_windows(model, data_dir, CONTEXT + GENERATED, limit)
  outcome = run_rollouts(model, trajectories, first=0, context=CONTEXT, horizon=1,
                         rng=jax.random.key(0), batch_size=batch_size,
                         task=frame_metrics_of("pusht"), keep_videos=8 if picture else 0)
  if picture:  # the first 8 windows: the simulator's frames above the model's, each 10 frames
    from wmjax.eval.video import frame_grid, write_png
    write_png(picture, frame_grid([v for pair in outcome.videos for v in pair]))
  state = trajectories.extras["state"].astype(np.float64)  # [W, T, 5]
  shift = np.abs(state[:, :, 2:4] - state[:, :1, 2:4]).max((1, 2))
  turn = np.degrees(np.abs(state[:, :, 4] - state[:, :1, 4]).max(1))
  still = (shift < 0.5) & (turn < 0.5)
  groups = {"all": np.ones(len(still), bool), "still": still, "moved": ~still}
  result = {"workdir": os.path.abspath(workdir), "step": int(model.step),
            "overrides": list(overrides), "params": params, "reference_data": builder_dir, "windows": int(len(still)),
            "still_windows": int(still.sum()), "context": CONTEXT, "generated": GENERATED,
            "episode": trajectories.episode.tolist(), "start": trajectories.start.tolist(),
            "still": still.tolist(), "per_window": {}}
  for name in ("block_iou", "block_error_px", "agent_error_px"):
    for who, values in (("model", outcome.model[name]), ("copy", outcome.copy_last[name])):
      for frames, label in ((slice(0, 1), "step1"), (slice(GENERATED - 1, GENERATED), "step8"),
                            (slice(0, GENERATED), "mean8")):
        per_window = np.nanmean(values[:, frames], axis=1)
        if who == "model":  # for comparisons paired by window between models
          result["per_window"][f"{name}/{label}"] = per_window.tolist()
        for group, keep in groups.items():
          mean, se, n = _episode_mean_se(per_window, trajectories.episode, keep)
          result[f"{name}/{who}/{label}/{group}"] = {"mean": mean, "se": se, "episodes": n}
  return result


def by_noise_level(workdir: str, step: int, data_dir: str, windows: int = 64) -> dict:
  """Does the model put the agent back from one noisy frame? For the first ``windows`` 3-frame
  windows of the reference ``test`` split: two clean frames, the third noised to each of
  :data:`LEVELS`, one call of the network; its x0 prediction's agent error and how often it draws
  an agent at all (``agent_error_px`` and ``agent_found`` of :mod:`wmjax.tasks.pusht.metrics`:
  a missing agent counts half the frame size). A model that draws the agent only
  where the noisy input still carries it, not from high noise, has not learnt where the context
  and the action put it."""
  import jax
  import jax.numpy as jnp

  from wmjax.frames import to_model
  from wmjax.model import load_model
  from wmjax.tasks.pusht.metrics import pusht_metrics

  model = load_model(workdir, step=step)
  _, batch = reference_windows(model, data_dir, 3, windows)
  frames, actions = jnp.asarray(to_model(batch.frames)), jnp.asarray(batch.actions)[:, :2]
  wm = model.world_model
  apply = jax.jit(wm.network.apply)
  rows = {}
  for level in LEVELS:
    levels = jnp.broadcast_to(jnp.asarray([-1, -1, level]), (len(frames), 3))
    noise = jax.random.normal(jax.random.key(level), frames[:, 2].shape)
    noisy = frames.at[:, 2].set(wm.process.add_noise(frames[:, 2], levels[:, 2], noise))
    out = apply(model.params, noisy, wm.process.model_time(levels), actions)[:, 2:]
    metrics = pusht_metrics(np.asarray(out), batch.frames[:, 2:], None)
    error = metrics["agent_error_px"][:, 0]
    rows[str(level)] = {"agent_error_px": float(error.mean()),
                        "agent_error_px_stderr": float(error.std(ddof=1) / np.sqrt(len(error))),
                        "agent_drawn": float(metrics["agent_found"].mean())}
  return {"workdir": os.path.abspath(workdir), "step": int(model.step),
          "windows": int(len(frames)), "levels": rows}


def first_frame_moves(trajectories) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Per window: the T centre's move (simulator units) and turn (degrees) from the last context
  frame into the first generated one, and copying the last context frame's T IoU there."""
  from wmjax.tasks.pusht.metrics import pusht_metrics
  state = trajectories.extras["state"].astype(np.float64)  # [W, T, 5]: agent xy, T xy, T angle
  c = CONTEXT
  shift = np.linalg.norm(state[:, c, 2:4] - state[:, c - 1, 2:4], axis=1)
  turn = np.degrees(np.abs(np.angle(np.exp(1j * (state[:, c, 4] - state[:, c - 1, 4])))))
  frames = trajectories.frames
  copy = pusht_metrics(frames[:, c - 1:c], frames[:, c:c + 1], None)["block_iou"][:, 0]
  return shift, turn, copy


def split_by_motion(workdir: str, data_dir: str, probe_files: list[str]) -> str:
  """A Markdown table of the probes in ``probe_files`` (this script's ``--out``): the model's T
  IoU at the first generated frame, and copying the last context frame's, for the windows of
  each of :data:`MOTION_GROUPS` by the simulator's T move into that frame. The windows are read
  again from the reference data, as ``workdir``'s model reads them."""
  from wmjax.model import load_model
  from wmjax.tasks.pusht.simulator import WORKSPACE

  _, trajectories = reference_windows(load_model(workdir), data_dir, CONTEXT + GENERATED)
  shift, turn, copy = first_frame_moves(trajectories)
  pixels = trajectories.frames.shape[3] / WORKSPACE
  where = {(e, s): i for i, (e, s) in enumerate(zip(trajectories.episode, trajectories.start))}
  lines = ["| probe | step | group | windows | T move, median (px) | turn, median (deg) | "
           "model T IoU | copy T IoU |", "|---|---|---|---|---|---|---|---|"]
  for path in probe_files:
    with open(path) as f:
      runs = json.load(f)
    name = os.path.join(*os.path.normpath(path).split(os.sep)[-2:])
    for run in runs if isinstance(runs, list) else [runs]:
      rows = np.asarray([where[(e, s)] for e, s in zip(run["episode"], run["start"])])
      iou = np.asarray(run["per_window"]["block_iou/step1"])
      for lo, hi, group in MOTION_GROUPS:
        keep = (shift[rows] >= lo) & (shift[rows] < hi)
        if keep.any():
          lines.append(f"| {name} | {run['step']} | {group} | {keep.sum()} | "
                       f"{np.median(shift[rows][keep]) * pixels:.2f} | "
                       f"{np.median(turn[rows][keep]):.1f} | {iou[keep].mean():.3f} | "
                       f"{copy[rows][keep].mean():.3f} |")
  return "\n".join(lines)


def paired(a: dict, b: dict, key: str, group: str = "all") -> tuple[float, float, int]:
  """``b`` minus ``a`` (two probes of the same windows) for ``per_window`` metric ``key``
  (e.g. ``block_iou/step8``) over the windows of ``group`` (all, still, moved): mean and standard
  error over episodes of each episode's mean difference, and the number of episodes."""
  if (a["episode"], a["start"]) != (b["episode"], b["start"]):
    raise ValueError("the two probes did not score the same windows")
  still = np.asarray(a["still"])
  keep = {"all": np.ones(len(still), bool), "still": still, "moved": ~still}[group]
  difference = np.asarray(b["per_window"][key]) - np.asarray(a["per_window"][key])
  return _episode_mean_se(difference, np.asarray(a["episode"]), keep)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--workdir", required=True, help="the model's workdir (checkpoints/)")
  parser.add_argument("--data_dir", required=True,
                      help="TFDS data directory holding (or to hold) the reference dataset")
  parser.add_argument("--step", type=int, action="append", default=[])
  parser.add_argument("--out", default=None, help="JSON file for every number")
  parser.add_argument("--limit", type=int, default=None, help="at most this many windows")
  parser.add_argument("--picture", default=None,
                      help="PNG of the first 8 windows (simulator above model); a path with "
                           "{step} in it when several steps are probed")
  parser.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                      help="an inference setting of the model's config (load_model's overrides), "
                           "e.g. sampling.num_steps=16; any number")
  parser.add_argument("--params", choices=("ema", "raw"), default="ema",
                      help="the checkpoint's EMA parameters (default) or its raw ones")
  parser.add_argument("--by_noise_level", action="store_true",
                      help="instead: the agent from one noisy frame at each noise level "
                           "(by_noise_level), 64 windows of 3 frames")
  parser.add_argument("--split_by_motion", action="append", default=[], metavar="PROBE_JSON",
                      help="instead: split these probes' first generated frame by the T's move "
                           "into it (split_by_motion); repeatable")
  args = parser.parse_args(argv)
  if args.split_by_motion:
    print(split_by_motion(args.workdir, args.data_dir, args.split_by_motion))
    return 0
  if not (args.step and args.out):
    parser.error("--step and --out are required (unless --split_by_motion)")
  results = []
  for step in args.step:
    if args.by_noise_level:
      results.append(by_noise_level(args.workdir, step, args.data_dir))
      for level, row in results[-1]["levels"].items():
        print(f"step {step}, level {level}: agent error {row['agent_error_px']:.1f} ± "
              f"{row['agent_error_px_stderr']:.1f} px, drawn in {row['agent_drawn']:.0%}")
      continue
    r = probe(args.workdir, step, args.data_dir, limit=args.limit,
              picture=args.picture and args.picture.format(step=step),
              overrides=tuple(args.override), params=args.params)
    results.append(r)

    def cell(key):
      v = r[key]
      return f"{v['mean']:.3f} ± {v['se']:.3f}"

    print(f"step {r['step']} ({r['windows']} windows, {r['still_windows']} with a still T): "
          f"T IoU step 1 {cell('block_iou/model/step1/all')} (copy "
          f"{cell('block_iou/copy/step1/all')}), step 8 {cell('block_iou/model/step8/all')} "
          f"(copy {cell('block_iou/copy/step8/all')}); still T step 8 "
          f"{cell('block_iou/model/step8/still')}, moved T step 8 "
          f"{cell('block_iou/model/step8/moved')} (copy {cell('block_iou/copy/step8/moved')}); "
          f"T error px step 8 {cell('block_error_px/model/step8/all')}; agent error px step 1 "
          f"{cell('agent_error_px/model/step1/all')}", flush=True)
  os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
  with open(args.out, "w") as f:
    json.dump(results, f, indent=2)
  return 0


if __name__ == "__main__":
  sys.exit(main())
