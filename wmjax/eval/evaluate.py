"""``wmjax evaluate``: the protocols (:mod:`wmjax.eval.protocols`) on a split of a checkpoint's
dataset, written out as ``metrics.json``, ``report.md`` and videos."""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
from typing import Callable, Sequence

import jax

from wmjax import registry
from wmjax.data.pipeline import member_configs
from wmjax.data.sources import open_dataset
from wmjax.eval.calibration import with_float8_scales
from wmjax.eval import video as video_lib
from wmjax.eval.frechet import FrechetDistances
from wmjax.eval.protocols import evaluate_protocols
from wmjax.eval.report import markdown_report, to_json_safe
from wmjax.model import load_model


def import_function(path: str | None) -> Callable | None:
  """``package.module:function`` -> the function (``None`` stays ``None``)."""
  if not path:
    return None
  module, sep, name = path.partition(":")
  if not sep:
    raise ValueError(f"expected package.module:function, got {path!r}")
  return getattr(importlib.import_module(module), name)


def evaluate_checkpoint(workdir: str, *, split: str | None = None, out: str | None = None,
                        protocols: Sequence[str] = ("short", "long", "sweep"),
                        step: int | None = None, params: str = "ema", batch_size: int = 16,
                        max_trajectories: int | None = None, videos: int = 4, num_sets: int = 4,
                        sweep_frames: int | None = None, seed: int = 0,
                        mask_key: str | None = None, frame_features: str | None = None,
                        clip_features: str | None = None, overrides: Sequence[str] = (),
                        param_dtype: str = "float32") -> tuple[str, dict]:
  """``wmjax evaluate``: the protocols on ``split`` of the checkpoint's dataset (default: the
  split its config holds out for evaluation, ``data.eval_split``); writes
  ``metrics.json``, ``report.md`` and ``videos/`` (ground truth | prediction | difference as mp4,
  and a PNG frame grid) to ``out`` (default ``WORKDIR/eval/SPLIT-stepN``). Returns (out, results)."""
  unknown = set(protocols) - {"short", "long", "sweep"}
  if unknown or not protocols:
    raise ValueError(f"protocols must be among short, long, sweep; got {list(protocols)}")
  model = load_model(workdir, step=step, params=params, overrides=overrides,
                     param_dtype=param_dtype)
  config = model.config  # completed on loading, its task imported
  data = member_configs(config.data)[0]  # a mixture is evaluated on its first dataset
  split = split or data.eval_split
  dataset = open_dataset(data)
  episodes = dataset.split(split)
  if mask_key:
    episodes.spec = dataclasses.replace(episodes.spec,
                                        extra_keys=episodes.spec.extra_keys + (mask_key,))
  resolution = dataset.resolution(episodes.spec)
  task = registry.frame_metrics_of(episodes.spec.name)
  normalize = model.normalize_actions
  model, float8 = with_float8_scales(model, jax.random.key(seed + 1), dataset)

  frechet = None
  if frame_features or clip_features:
    frechet = FrechetDistances(import_function(frame_features), import_function(clip_features))
  results, kept = evaluate_protocols(
      model, episodes, protocols=protocols, rng=jax.random.key(seed), batch_size=batch_size,
      max_trajectories=max_trajectories, keep_videos=videos, num_sets=num_sets,
      sweep_frames=sweep_frames or 2 * config.rollout.horizon, resolution=resolution,
      normalize=normalize, frechet=frechet, mask_name=mask_key.split("/")[-1] if mask_key else None,
      task=task)
  out = out or os.path.join(workdir, "eval", f"{split}-step{model.step}")
  os.makedirs(out, exist_ok=True)
  header = (f"# wmjax evaluate: {config.name} step {model.step} ({params} parameters), "
            f"split {split!r}, {data.dataset}")
  results = dict(results, workdir=os.path.abspath(workdir), step=model.step, split=split,
                 params=params, sampler=config.sampling.to_dict(),
                 **({"float8": float8} if float8 else {}))
  with open(os.path.join(out, "metrics.json"), "w") as f:
    json.dump(to_json_safe(results), f, indent=2)
  with open(os.path.join(out, "report.md"), "w") as f:
    f.write(markdown_report(results, header, task))
  fps = 4.0 if config.frame_shape[0] <= 64 else 8.0
  for protocol, pairs in kept.items():
    for i, (truth, pred) in enumerate(pairs):
      name = os.path.join(out, "videos", f"{protocol}_{i:03d}")
      video_lib.write_video(name + ".mp4", video_lib.comparison(truth, pred), fps=fps)
      video_lib.write_png(name + ".png", video_lib.frame_grid(
          [truth, pred, video_lib.difference(pred, truth)]))
  return out, results
