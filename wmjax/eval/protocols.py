"""The evaluation protocols behind ``wmjax evaluate``, on a held-out split of the training data.

IRASim (appendix 11):
  ``short``  windows of ``1 + H`` frames taken with stride ``1 + H`` from every episode
             (``H = model.num_frames - 1``: 15 for IRASim); one block of ``H`` frames from the
             first frame under the ``H`` true actions.
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

import dataclasses
import functools
import importlib
import json
import os
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.data import gridworld, oxe
from wmjax.data.pipeline import WindowSource
from wmjax.data.rlds import make_window
from wmjax.data.sources import ArrayRecordEpisodes, dataset_dir
from wmjax.eval import metrics
from wmjax.eval import video as video_lib
from wmjax.frames import to_model, to_uint8, to_unit
from wmjax.model import LoadedModel, load_model
from wmjax.parallel import shard_rollout_batch
from wmjax.rollout import rollout
from wmjax.train.data import member_configs

# name -> whether lower is better (for the report)
METRICS = {"mse": True, "psnr": False, "ssim": False, "gray_psnr": False, "gray_ssim": False,
           "latent_l2": True, "masked_mse": True, "square_error_px": True, "square_iou": False,
           "square_one_component": False}


@dataclasses.dataclass
class Trajectories:
  """Held-out trajectories padded to a common length ``T``: frames uint8 ``[E, T, H, W, 3]``,
  normalised actions ``[E, T-1, A]``, true lengths ``[E]``, per-step extras ``[E, T, ...]``
  (e.g. ``square_positions``, ``masks``), and where each came from (episode, start step)."""

  frames: np.ndarray
  actions: np.ndarray
  lengths: np.ndarray
  extras: dict[str, np.ndarray]
  episode: np.ndarray
  start: np.ndarray

  def __len__(self) -> int:
    return len(self.frames)

  @classmethod
  def stack(cls, windows: Sequence[dict], normalize: Callable[[np.ndarray], np.ndarray]
            ) -> "Trajectories":
    """Windows of :func:`wmjax.data.rlds.make_window` (any lengths) -> padded trajectories."""
    if not windows:
      raise ValueError("no trajectories to evaluate")
    lengths = np.array([len(w["frames"]) for w in windows])
    t = int(lengths.max())

    def pad(x, length):
      x = np.asarray(x)
      return np.concatenate([x, np.zeros((length - len(x),) + x.shape[1:], x.dtype)])

    extras = {k: np.stack([pad(w[k], t) for w in windows]) for k in windows[0]
              if k not in ("frames", "actions", "instruction", "episode", "start")}
    return cls(np.stack([pad(w["frames"], t) for w in windows]),
               np.stack([pad(normalize(w["actions"]), t - 1) for w in windows]), lengths, extras,
               np.array([w["episode"] for w in windows]), np.array([w["start"] for w in windows]))

  def take(self, index) -> "Trajectories":
    return Trajectories(self.frames[index], self.actions[index], self.lengths[index],
                        {k: v[index] for k, v in self.extras.items()}, self.episode[index],
                        self.start[index])


def windows_of(episodes: ArrayRecordEpisodes, length: int, resolution, limit: int | None
               ) -> list[dict]:
  """Windows of ``length`` frames with stride ``length`` (IRASim's short trajectories)."""
  source = WindowSource(episodes, length, length, resolution)
  return [source[k] for k in range(min(len(source), limit or len(source)))]


def whole_episodes(episodes: ArrayRecordEpisodes, resolution, min_length: int,
                   limit: int | None) -> list[dict]:
  """Every episode of at least ``min_length`` steps, whole (IRASim's long trajectories)."""
  lengths = episodes.lengths()
  chosen = [e for e in range(len(lengths)) if lengths[e] >= min_length][:limit]
  return [make_window(episodes.episode(e), 0, int(lengths[e]), resolution, e,
                      episodes.spec.resize) for e in chosen]


def _as_masks(masks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """Per-step masks ``[E, T, h, w(, 1)]`` -> bool ``[E, T, H, W]`` (nearest-neighbour resize)."""
  from PIL import Image
  masks = np.asarray(masks)
  if masks.ndim == 5 and masks.shape[-1] == 1:
    masks = masks[..., 0]
  if masks.ndim != 4:
    raise ValueError(f"masks must be [h, w] or [h, w, 1] per step, got {masks.shape[2:]}")
  if masks.shape[2:] != tuple(size):
    resized = [np.asarray(Image.fromarray(m.astype(np.uint8)).resize(size[::-1], Image.NEAREST))
               for m in masks.reshape((-1,) + masks.shape[2:])]
    masks = np.stack(resized).reshape(masks.shape[:2] + tuple(size))
  return masks > 0


# ----------------------------------------------------------------------------- metrics


def frame_metrics(pred, truth, extras: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  """Per-frame pixel metrics ``[E, T]`` of ``pred`` against ``truth`` (both ``[E, T, H, W, C]``
  RGB, the generated frames only); ``extras`` hold per-frame ``square_positions`` / ``masks``
  when the data has them. SSIM needs frames of at least 11 (colour) / 7 (grayscale) pixels."""
  result = {"mse": metrics.mse(pred, truth), "psnr": metrics.psnr(pred, truth)}
  h, w, c = np.shape(truth)[-3:]
  if c == 3:
    if min(h, w) >= 11:
      result["ssim"] = metrics.ssim(pred, truth, "gaussian")
    gray_pred, gray_truth = metrics.grayscale(pred), metrics.grayscale(truth)
    result["gray_psnr"] = metrics.psnr(gray_pred * 2 - 1, gray_truth * 2 - 1)
    if min(h, w) >= 7:
      result["gray_ssim"] = metrics.ssim(gray_pred * 2 - 1, gray_truth * 2 - 1, "uniform")
  if "masks" in extras:
    result["masked_mse"] = metrics.masked_mse(pred, truth, extras["masks"])
  if "square_positions" in extras and "masks" not in extras:
    centres = extras["square_positions"]
    colors = gridworld.COLORS[:centres.shape[-2]]
    error, _ = metrics.square_position_error(pred, centres, colors, missing_penalty=h / 2)
    result["square_error_px"] = error.mean(-1)
    iou, one_component = metrics.square_iou(pred, truth, colors)
    result["square_iou"] = iou.mean(-1)
    result["square_one_component"] = one_component.mean(-1)
    # object masks: the squares' pixels in the truth or the prediction
    masks = (metrics.color_masks(truth, colors) | metrics.color_masks(pred, colors)).any(-1)
    result["masked_mse"] = metrics.masked_mse(pred, truth, masks)
  return {k: np.asarray(v, np.float64) for k, v in result.items()}


def _summarize(per_frame: dict[str, np.ndarray]) -> dict[str, dict]:
  """``[E, T]`` with NaN for missing frames -> mean / stderr over trajectories + curve."""
  out = {}
  for name, values in per_frame.items():
    per_trajectory, _ = metrics.mean_stderr(values, axis=1)  # NaN for a trajectory without frames
    mean, stderr = metrics.mean_stderr(per_trajectory)
    curve_mean, curve_stderr = metrics.mean_stderr(values, axis=0)
    out[name] = {"mean": float(mean), "stderr": float(stderr),
                 "per_frame": np.asarray(curve_mean).tolist(),
                 "per_frame_stderr": np.asarray(curve_stderr).tolist()}
  return out


# ----------------------------------------------------------------------------- rollouts


@dataclasses.dataclass
class Outcome:
  """Per-frame metrics ``[E, T']`` (NaN past a trajectory's end) of the model and of the
  copy-last baseline over the generated frames, and the predictions kept for videos."""

  model: dict[str, np.ndarray]
  copy_last: dict[str, np.ndarray]
  videos: list[tuple[np.ndarray, np.ndarray]]  # (truth, prediction) uint8 [T, H, W, 3]

  def summary(self) -> dict:
    return {"model": _summarize(self.model), "copy_last": _summarize(self.copy_last),
            "trajectories": len(next(iter(self.model.values())))}


def run_rollouts(model: LoadedModel, trajectories: Trajectories, *, first: int, context: int,
                 horizon: int, rng: jax.Array, batch_size: int, keep_videos: int = 0,
                 frechet: "FrechetDistances | None" = None, baseline: bool = True) -> Outcome:
  """Roll out every trajectory from its frames ``[first, first + context)`` under its actions
  (batches of ``batch_size``, padded so that one compilation serves all) and score the frames
  from ``first + context`` on against the truth (and feed ``frechet``, if given); the
  copy-last-frame baseline is scored too unless ``baseline`` is False."""
  start = first + context
  lengths = trajectories.lengths
  if (lengths <= start).any():
    raise ValueError(f"every trajectory needs more than {start} frames; shortest has "
                     f"{lengths.min()}")
  per_model: dict[str, list] = {}
  per_copy: dict[str, list] = {}
  videos = []
  for index, lo in enumerate(range(0, len(trajectories), batch_size)):
    take = np.arange(lo, min(lo + batch_size, len(trajectories)))
    padded = np.concatenate([take, np.full(batch_size - len(take), take[-1])])
    batch = trajectories.take(padded)
    steps = np.arange(batch.actions.shape[1])[None]
    known = steps < (batch.lengths - 1)[:, None]
    encode_key, rollout_key = jax.random.split(jax.random.fold_in(rng, index))
    frames, actions, mask = shard_rollout_batch(  # the batch is split over the local devices
        to_model(batch.frames[:, first:]), batch.actions, known)
    latents = model.codec.encode(frames, encode_key)
    generated = rollout(
        model.world_model, model.params, latents[:, :context], actions[:, start - 1:],
        rollout_key, horizon=horizon, action_mask=mask[:, start - 1:],
        context_actions=actions[:, first:start - 1] if context > 1 else None)
    generated = generated[:len(take), context:]
    truth_latents = latents[:len(take), context - 1:]  # the last context frame, then the targets
    predicted = to_uint8(model.codec.decode(generated))
    truth = batch.frames[:len(take), start:]
    extras = {k: v[:len(take), start:] for k, v in batch.extras.items()}
    valid = (np.arange(truth.shape[1])[None] + start) < batch.lengths[:len(take), None]
    copy = np.broadcast_to(batch.frames[:len(take), start - 1:start], truth.shape)
    if frechet is not None:
      frechet.update(truth, predicted)
    copy_latents = jnp.broadcast_to(truth_latents[:, :1], generated.shape)
    candidates = [(per_model, predicted, generated)]
    if baseline:
      candidates.append((per_copy, copy, copy_latents))
    for store, pred, pred_latents in candidates:
      values = frame_metrics(pred, truth, extras)
      values["latent_l2"] = np.asarray(metrics.latent_l2(pred_latents, truth_latents[:, 1:]))
      for name, value in values.items():
        store.setdefault(name, []).append(np.where(valid, value, np.nan))
    for i in range(len(take)):
      if len(videos) < keep_videos:
        n = lengths[take[i]] - start
        videos.append((batch.frames[i, first:start + n],
                       np.concatenate([batch.frames[i, first:start], predicted[i, :n]])))
  return Outcome({k: np.concatenate(v) for k, v in per_model.items()},
                 {k: np.concatenate(v) for k, v in per_copy.items()}, videos)


# ----------------------------------------------------------------------------- Fréchet distances


FeatureFn = Callable[[jax.Array], jax.Array]


class FrechetDistances:
  """FID over frames and FVD over clips from user-supplied feature networks:
  ``frame_features([N, H, W, 3] in [0, 1]) -> [N, D]`` and ``clip_features([N, T, H, W, 3] in
  [0, 1]) -> [N, D]`` (e.g. a Flax InceptionV3 / I3D ``apply`` closed over its weights). Used on
  equal-length clips (IRASim computes them for short trajectories only)."""

  def __init__(self, frame_features: FeatureFn | None, clip_features: FeatureFn | None):
    self.functions = {"fid": frame_features, "fvd": clip_features}
    self.moments = {name: (metrics.FeatureMoments(), metrics.FeatureMoments())
                    for name, fn in self.functions.items() if fn is not None}

  def update(self, truth: np.ndarray, predicted: np.ndarray) -> None:
    """``truth``, ``predicted``: uint8 clips ``[N, T, H, W, 3]``."""
    for name, (real, fake) in self.moments.items():
      for moments, clips in ((real, truth), (fake, predicted)):
        x = to_unit(clips)
        if name == "fid":
          x = x.reshape((-1,) + x.shape[2:])
        moments.update(np.asarray(self.functions[name](x)).reshape(len(x), -1))

  def result(self) -> dict[str, float]:
    return {name: metrics.frechet_distance(real, fake)
            for name, (real, fake) in self.moments.items()}


# ----------------------------------------------------------------------------- protocols


def sweep_settings(num_frames: int, context: int, horizon: int,
                   values: Sequence[int] = (1, 2, 4, 8, 16)) -> list[tuple[int, int]]:
  """WPE figure 7: (c, h) pairs varying c at the config's h, and h at the config's c, that fit
  ``num_frames``; the config's own setting included."""
  contexts = sorted({v for v in values if v + horizon <= num_frames} | {context})
  horizons = sorted({v for v in values if context + v <= num_frames} | {horizon})
  return sorted({(c, horizon) for c in contexts} | {(context, h) for h in horizons})


def wpe_sweep(model: LoadedModel, trajectories: Trajectories, settings: Sequence[tuple[int, int]],
              *, num_sets: int, rng: jax.Array, batch_size: int) -> list[dict]:
  """Every (c, h) setting on the same target frames (after the longest context), ``num_sets``
  generations each; metrics are mean and standard error over the sets. The copy-last baseline
  (the frame before the targets) is the same for every setting and is scored once."""
  longest = max(c for c, _ in settings)
  rows = []
  copy = None
  for c, h in settings:
    set_means: dict[str, list] = {}
    for s in range(num_sets):
      outcome = run_rollouts(model, trajectories, first=longest - c, context=c, horizon=h,
                             rng=jax.random.fold_in(rng, s), batch_size=batch_size,
                             baseline=copy is None)
      for name, values in outcome.model.items():
        set_means.setdefault(name, []).append(float(np.nanmean(values)))
      copy = copy or {name: float(np.nanmean(v)) for name, v in outcome.copy_last.items()}
    row = {"context": c, "horizon": h, "sets": num_sets, "copy_last": copy}
    for name, values in set_means.items():
      mean, stderr = metrics.mean_stderr(values)
      row[name] = {"mean": float(mean), "stderr": float(stderr)}
    rows.append(row)
  return rows


def evaluate_protocols(model: LoadedModel, episodes: ArrayRecordEpisodes, *,
                       protocols: Sequence[str], rng: jax.Array, batch_size: int,
                       max_trajectories: int | None, keep_videos: int, num_sets: int,
                       sweep_frames: int, resolution, normalize,
                       frechet: FrechetDistances | None = None, mask_name: str | None = None
                       ) -> tuple[dict, dict]:
  """Run the named protocols (``short``, ``long``, ``sweep``); returns (results, videos).
  ``frechet`` (FID / FVD) is computed on the short trajectories; ``mask_name`` names the per-step
  extra that holds masks for the masked MSE."""

  def stack(windows):
    trajectories = Trajectories.stack(windows, normalize)
    if mask_name:
      trajectories.extras["masks"] = _as_masks(trajectories.extras.pop(mask_name),
                                               trajectories.frames.shape[2:4])
    return trajectories

  config = model.config
  c, h = config.rollout.context, config.rollout.horizon
  num_frames = config.model.num_frames
  results, videos = {}, {}
  if "short" in protocols:
    windows = windows_of(episodes, num_frames, resolution, max_trajectories)
    outcome = run_rollouts(model, stack(windows), first=0, context=1,
                           horizon=num_frames - 1, rng=jax.random.fold_in(rng, 0),
                           batch_size=batch_size, keep_videos=keep_videos, frechet=frechet)
    results["short"] = dict(outcome.summary(), context=1, horizon=num_frames - 1)
    if frechet is not None:
      results["short"]["frechet"] = frechet.result()
    videos["short"] = outcome.videos
  if "long" in protocols:
    windows = whole_episodes(episodes, resolution, c + 1, max_trajectories)
    trajectories = stack(windows)
    outcome = run_rollouts(model, trajectories, first=0, context=c, horizon=h,
                           rng=jax.random.fold_in(rng, 1), batch_size=batch_size,
                           keep_videos=keep_videos)
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
                          batch_size=batch_size)}
  return results, videos


# ----------------------------------------------------------------------------- report


def _cell(entry: dict, digits: int = 4) -> str:
  if not np.isfinite(entry["stderr"]):
    return f"{entry['mean']:.{digits}g}"
  return f"{entry['mean']:.{digits}g} ± {entry['stderr']:.2g}"


def markdown_report(results: dict, header: str) -> str:
  """The results as Markdown tables: IRASim short / long (model vs copy-last, per-frame curves
  of the first metric) and the WPE sweep."""
  lines = [header, ""]
  for name, title in (("short", "IRASim short trajectories"), ("long", "IRASim long trajectories")):
    if name not in results:
      continue
    r = results[name]
    lines += [f"## {title} (c={r['context']}, h={r['horizon']}, {r['trajectories']} "
              f"trajectories)", "", "| metric | model | copy last frame | better |",
              "|---|---|---|---|"]
    for metric, lower in METRICS.items():
      if metric in r["model"]:
        m, b = r["model"][metric], r["copy_last"][metric]
        better = "model" if (m["mean"] < b["mean"]) == lower else "copy-last"
        lines.append(f"| {metric}{' ↓' if lower else ' ↑'} | {_cell(m)} | {_cell(b)} | {better} |")
    key = "square_error_px" if "square_error_px" in r["model"] else "mse"
    curve, base = r["model"][key]["per_frame"], r["copy_last"][key]["per_frame"]
    shown = np.unique(np.linspace(0, len(curve) - 1, min(len(curve), 16)).round().astype(int))
    lines += ["", f"{key} per generated frame (model / copy-last):", "",
              "| frame | " + " | ".join(str(i + 1) for i in shown) + " |",
              "|---" * (len(shown) + 1) + "|",
              "| model | " + " | ".join(f"{curve[i]:.3g}" for i in shown) + " |",
              "| copy last | " + " | ".join(f"{base[i]:.3g}" for i in shown) + " |", ""]
  if "sweep" in results:
    rows = results["sweep"]["rows"]
    names = [m for m in METRICS if m in rows[0]]
    lines += [f"## WPE context / horizon sweep ({results['sweep']['target_frames']} target "
              f"frames, mean ± stderr over {rows[0]['sets']} sets)", "",
              "| c | h | " + " | ".join(names) + " |", "|---|---" + "|---" * len(names) + "|"]
    for row in rows:
      lines.append(f"| {row['context']} | {row['horizon']} | "
                   + " | ".join(_cell(row[n]) for n in names) + " |")
    copy = rows[0]["copy_last"]
    lines.append("| copy last | | " + " | ".join(f"{copy[n]:.4g}" for n in names) + " |")
  return "\n".join(lines) + "\n"


def to_json_safe(value: Any) -> Any:
  """NaN / inf -> None, recursively (JSON has no NaN)."""
  if isinstance(value, dict):
    return {k: to_json_safe(v) for k, v in value.items()}
  if isinstance(value, (list, tuple)):
    return [to_json_safe(v) for v in value]
  if isinstance(value, float) and not np.isfinite(value):
    return None
  return value


# ----------------------------------------------------------------------------- whole command


def import_function(path: str | None) -> Callable | None:
  """``package.module:function`` -> the function (``None`` stays ``None``)."""
  if not path:
    return None
  module, sep, name = path.partition(":")
  if not sep:
    raise ValueError(f"expected package.module:function, got {path!r}")
  return getattr(importlib.import_module(module), name)


def evaluate_checkpoint(workdir: str, *, split: str, out: str | None = None,
                        protocols: Sequence[str] = ("short", "long", "sweep"),
                        step: int | None = None, params: str = "ema", batch_size: int = 16,
                        max_trajectories: int | None = None, videos: int = 4, num_sets: int = 4,
                        sweep_frames: int | None = None, seed: int = 0,
                        mask_key: str | None = None, frame_features: str | None = None,
                        clip_features: str | None = None, overrides: Sequence[str] = (),
                        param_dtype: str = "float32") -> tuple[str, dict]:
  """``wmjax evaluate``: the protocols on ``split`` of the checkpoint's dataset; writes
  ``metrics.json``, ``report.md`` and ``videos/`` (ground truth | prediction | difference as mp4,
  and a PNG frame grid) to ``out`` (default ``WORKDIR/eval/SPLIT-stepN``). Returns (out, results)."""
  unknown = set(protocols) - {"short", "long", "sweep"}
  if unknown or not protocols:
    raise ValueError(f"protocols must be among short, long, sweep; got {list(protocols)}")
  model = load_model(workdir, step=step, params=params, overrides=overrides,
                     param_dtype=param_dtype)
  config = model.config
  data = member_configs(config.data)[0]  # a mixture is evaluated on its first dataset
  episodes = ArrayRecordEpisodes(dataset_dir(data), split, oxe.specs_from_config(data))
  if mask_key:
    episodes.spec = dataclasses.replace(episodes.spec,
                                        extra_keys=episodes.spec.extra_keys + (mask_key,))
  resolution = tuple(data.get("resolution") or episodes.spec.resolution)
  normalize = functools.partial(model.action_stats.normalize, mode=config.data.normalization,
                                pad_to=config.model.action_dim)

  frechet = None
  if frame_features or clip_features:
    frechet = FrechetDistances(import_function(frame_features), import_function(clip_features))
  results, kept = evaluate_protocols(
      model, episodes, protocols=protocols, rng=jax.random.key(seed), batch_size=batch_size,
      max_trajectories=max_trajectories, keep_videos=videos, num_sets=num_sets,
      sweep_frames=sweep_frames or 2 * config.rollout.horizon, resolution=resolution,
      normalize=normalize, frechet=frechet, mask_name=mask_key.split("/")[-1] if mask_key else None)
  out = out or os.path.join(workdir, "eval", f"{split}-step{model.step}")
  os.makedirs(out, exist_ok=True)
  header = (f"# wmjax evaluate: {config.get('name', '')} step {model.step} ({params} parameters), "
            f"split {split!r}, {data.dataset}")
  results = dict(results, workdir=os.path.abspath(workdir), step=model.step, split=split,
                 params=params, sampler=config.sampling.to_dict())
  with open(os.path.join(out, "metrics.json"), "w") as f:
    json.dump(to_json_safe(results), f, indent=2)
  with open(os.path.join(out, "report.md"), "w") as f:
    f.write(markdown_report(results, header))
  fps = 4.0 if config.frame_shape[0] <= 64 else 8.0
  for protocol, pairs in kept.items():
    for i, (truth, pred) in enumerate(pairs):
      name = os.path.join(out, "videos", f"{protocol}_{i:03d}")
      video_lib.write_video(name + ".mp4", video_lib.comparison(truth, pred), fps=fps)
      video_lib.write_png(name + ".png", video_lib.frame_grid(
          [truth, pred, video_lib.difference(pred, truth)]))
  return out, results
