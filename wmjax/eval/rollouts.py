"""Batched rollouts of held-out trajectories, scored frame by frame against the truth and against
the copy-last-frame baseline."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.eval import metrics
from wmjax.eval.frechet import FrechetDistances
from wmjax.eval.trajectories import Trajectories
from wmjax.frames import to_model, to_uint8
from wmjax.model import LoadedModel
from wmjax.parallel import shard_rollout_batch
from wmjax.progress import Progress
from wmjax.rollout import rollout
from wmjax.registry import FrameMetrics


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


def latent_l2_left_out(model: LoadedModel) -> str | None:
  """Why ``latent_l2`` is not scored for ``model``, or None when it is.

  IRASim's latent L2 compares raw values of a codec's space, which means something only where
  that space has a fixed scale: pixels, patches, a trained VAE's latents. A randomly initialised
  VAE (``codec.random_vae``) gives latents of an arbitrary scale (tens of thousands where the
  model's own outputs are clipped near [-1, 1]), so the number would compare nothing."""
  codec = model.config.get("codec")
  if codec is not None and codec.get("random_vae"):
    return (f"latent_l2 left out: the codec is a randomly initialised {codec.random_vae} VAE, "
            f"whose latents have no fixed scale to compare raw values in")
  return None


@dataclasses.dataclass
class Outcome:
  """Per-frame metrics ``[E, T']`` (NaN past a trajectory's end) of the model and of the
  copy-last baseline over the generated frames, and the predictions kept for videos."""

  model: dict[str, np.ndarray]
  copy_last: dict[str, np.ndarray]
  videos: list[tuple[np.ndarray, np.ndarray]]  # (truth, prediction) uint8 [T, H, W, 3]
  left_out: tuple[str, ...] = ()  # why a metric was not scored, one sentence each

  def summary(self) -> dict:
    summary = {"model": _summarize(self.model), "copy_last": _summarize(self.copy_last),
               "trajectories": len(next(iter(self.model.values())))}
    if self.left_out:
      summary["left_out"] = list(self.left_out)
    return summary


def run_rollouts(model: LoadedModel, trajectories: Trajectories, *, first: int, context: int,
                 horizon: int, rng: jax.Array, batch_size: int, keep_videos: int = 0,
                 frechet: FrechetDistances | None = None, baseline: bool = True,
                 task: FrameMetrics | None = None, progress: str | None = None) -> Outcome:
  """Roll out every trajectory from its frames ``[first, first + context)`` under its actions
  (batches of ``batch_size``, padded so that one compilation serves all; the frames encoded by
  the model's codec, or the trajectories' own latents where they carry them) and score the frames
  from ``first + context`` on against the truth (and feed ``frechet``, if given); the
  copy-last-frame baseline is scored too unless ``baseline`` is False; ``task`` adds the
  dataset's own metrics (:func:`wmjax.eval.metrics.frame_metrics`); ``progress`` names the loop
  in progress lines (:class:`wmjax.progress.Progress`), None shows none."""
  start = first + context
  lengths = trajectories.lengths
  if (lengths <= start).any():
    raise ValueError(f"every trajectory needs more than {start} frames; shortest has "
                     f"{lengths.min()}")
  per_model: dict[str, list] = {}
  per_copy: dict[str, list] = {}
  videos = []
  latent_reason = latent_l2_left_out(model)
  tracker = Progress(progress, len(trajectories), "trajectories") if progress else None
  for index, lo in enumerate(range(0, len(trajectories), batch_size)):
    take = np.arange(lo, min(lo + batch_size, len(trajectories)))
    padded = np.concatenate([take, np.full(batch_size - len(take), take[-1])])
    batch = trajectories.take(padded)
    steps = np.arange(batch.actions.shape[1])[None]
    known = steps < (batch.lengths - 1)[:, None]
    encode_key, rollout_key = jax.random.split(jax.random.fold_in(rng, index))
    frames, actions, mask = shard_rollout_batch(  # the batch is split over the local devices
        to_model(batch.frames[:, first:]), batch.actions, known)
    latents = (model.codec.encode(frames, encode_key) if batch.latents is None
               else shard_rollout_batch(batch.latents[:, first:])[0])
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
      values = metrics.frame_metrics(pred, truth, extras, task)
      if latent_reason is None:
        values["latent_l2"] = np.asarray(metrics.latent_l2(pred_latents, truth_latents[:, 1:]))
      for name, value in values.items():
        store.setdefault(name, []).append(np.where(valid, value, np.nan))
    for i in range(len(take)):
      if len(videos) < keep_videos:
        n = lengths[take[i]] - start
        videos.append((batch.frames[i, first:start + n],
                       np.concatenate([batch.frames[i, first:start], predicted[i, :n]])))
    if tracker:
      tracker.update(len(take))
  if tracker:
    tracker.close()
  return Outcome({k: np.concatenate(v) for k, v in per_model.items()},
                 {k: np.concatenate(v) for k, v in per_copy.items()}, videos,
                 () if latent_reason is None else (latent_reason,))
