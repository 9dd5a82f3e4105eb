"""The evaluation protocols behind ``wmjax evaluate``, on a held-out split of the training data.

IRASim (appendix 11):
  ``short``  windows of ``1 + H`` frames taken with stride ``1 + H`` from every episode
             (``H = rollout.short_actions``, by default ``model.num_frames - 1``: 15 for
             IRASim); the ``H`` frames after the first under the ``H`` true actions, in one block
             or, for a model whose window is shorter, chained blocks of ``num_frames - 1``.
  ``long``   whole episodes: from the first ``rollout.context`` frames, blocks of
             ``rollout.horizon`` frames chained to the end of the episode.
WPE (figure 7): a context / horizon sweep. One of ``c`` and ``h`` stays at the config's value
while the other varies; every setting predicts the same target frames (the ``L`` frames after the
longest context, ``c`` true frames before them as context), and ``num_sets`` independent
generations (seeds) give the mean and standard error of each metric.

Every metric is computed per generated frame (context frames skipped) for the model and for the
copy-last-frame baseline; a trajectory's score is the mean over its frames, a protocol's the mean
and standard error over trajectories (sweep: over sets), and per-frame curves average each frame
index over the trajectories that reach it.
"""

from __future__ import annotations

from typing import Sequence

import jax
import numpy as np

from wmjax.data.sources import ArrayRecordEpisodes
from wmjax.eval import metrics
from wmjax.eval.frechet import FrechetDistances
from wmjax.eval.rollouts import run_rollouts
from wmjax.eval.trajectories import Trajectories, as_masks, whole_episodes, windows_of
from wmjax.model import LoadedModel
from wmjax.progress import Progress
from wmjax.registry import FrameMetrics


def sweep_settings(num_frames: int, context: int, horizon: int,
                   values: Sequence[int] = (1, 2, 4, 8, 16)) -> list[tuple[int, int]]:
  """WPE figure 7: (c, h) pairs varying c at the config's h, and h at the config's c, that fit
  ``num_frames``; the config's own setting included."""
  contexts = sorted({v for v in values if v + horizon <= num_frames} | {context})
  horizons = sorted({v for v in values if context + v <= num_frames} | {horizon})
  return sorted({(c, horizon) for c in contexts} | {(context, h) for h in horizons})


def wpe_sweep(model: LoadedModel, trajectories: Trajectories, settings: Sequence[tuple[int, int]],
              *, num_sets: int, rng: jax.Array, batch_size: int,
              task: FrameMetrics | None = None) -> list[dict]:
  """Every (c, h) setting on the same target frames (after the longest context), ``num_sets``
  generations each; metrics are mean and standard error over the sets. The copy-last baseline
  (the frame before the targets) is the same for every setting and is scored once."""
  longest = max(c for c, _ in settings)
  rows = []
  copy = None
  tracker = Progress("evaluate sweep", len(settings) * num_sets, "rollout sets")
  for c, h in settings:
    set_means: dict[str, list] = {}
    for s in range(num_sets):
      outcome = run_rollouts(model, trajectories, first=longest - c, context=c, horizon=h,
                             rng=jax.random.fold_in(rng, s), batch_size=batch_size,
                             baseline=copy is None, task=task)
      tracker.update()
      for name, values in outcome.model.items():
        set_means.setdefault(name, []).append(float(np.nanmean(values)))
      copy = copy or {name: float(np.nanmean(v)) for name, v in outcome.copy_last.items()}
    row = {"context": c, "horizon": h, "sets": num_sets, "copy_last": copy}
    for name, values in set_means.items():
      mean, stderr = metrics.mean_stderr(values)
      row[name] = {"mean": float(mean), "stderr": float(stderr)}
    rows.append(row)
  tracker.close()
  return rows


def evaluate_protocols(model: LoadedModel, episodes: ArrayRecordEpisodes, *,
                       protocols: Sequence[str], rng: jax.Array, batch_size: int,
                       max_trajectories: int | None, keep_videos: int, num_sets: int,
                       sweep_frames: int, resolution, normalize,
                       frechet: FrechetDistances | None = None, mask_name: str | None = None,
                       task: FrameMetrics | None = None) -> tuple[dict, dict]:
  """Run the named protocols (``short``, ``long``, ``sweep``); returns (results, videos).
  ``frechet`` (FID / FVD) is computed on the short trajectories; ``mask_name`` names the per-step
  extra that holds masks for the masked MSE; ``task`` adds the dataset's own metrics."""

  def stack(windows):
    trajectories = Trajectories.stack(windows, normalize)
    if mask_name:
      trajectories.extras["masks"] = as_masks(trajectories.extras.pop(mask_name),
                                               trajectories.frames.shape[2:4])
    return trajectories

  config = model.config
  c, h = config.rollout.context, config.rollout.horizon
  num_frames = config.model.num_frames
  results, videos = {}, {}
  if "short" in protocols:
    actions = config.rollout.short_actions
    if actions is None:
      actions = num_frames - 1
    elif actions < 1:
      raise ValueError(f"rollout.short_actions must be a positive number of actions or None, "
                       f"got {actions}")
    windows = windows_of(episodes, 1 + actions, resolution, max_trajectories)
    block = min(actions, num_frames - 1)
    outcome = run_rollouts(model, stack(windows), first=0, context=1, horizon=block,
                           rng=jax.random.fold_in(rng, 0), batch_size=batch_size,
                           keep_videos=keep_videos, frechet=frechet, task=task,
                           progress="evaluate short")
    results["short"] = dict(outcome.summary(), context=1, horizon=block, actions=actions)
    if frechet is not None:
      results["short"]["frechet"] = frechet.result()
    videos["short"] = outcome.videos
  if "long" in protocols:
    windows = whole_episodes(episodes, resolution, c + 1, max_trajectories)
    trajectories = stack(windows)
    outcome = run_rollouts(model, trajectories, first=0, context=c, horizon=h,
                           rng=jax.random.fold_in(rng, 1), batch_size=batch_size,
                           keep_videos=keep_videos, task=task, progress="evaluate long")
    results["long"] = dict(outcome.summary(), context=c, horizon=h,
                           mean_length=float(trajectories.lengths.mean()))
    videos["long"] = outcome.videos
  if "sweep" in protocols:
    settings = sweep_settings(num_frames, c, h)
    longest = max(s[0] for s in settings)
    windows = windows_of(episodes, longest + sweep_frames, resolution, max_trajectories)
    results["sweep"] = {
        "target_frames": sweep_frames,
        "rows": wpe_sweep(model, stack(windows), settings,
                          num_sets=num_sets, rng=jax.random.fold_in(rng, 2),
                          batch_size=batch_size, task=task)}
  return results, videos
