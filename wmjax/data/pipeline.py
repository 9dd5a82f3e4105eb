"""grain input pipeline over ArrayRecord RLDS: random-access windows, deterministic shuffling,
sharding by process, weighted mixtures, normalisation and batching, checkpointable iterators.

  sources = [WindowSource(ArrayRecordEpisodes(dir, "train"), frames=16, stride=1,
                          resolution=(256, 320))]
  ds = training_pipeline(sources, [stats], batch_size=8, seed=0)
  it = iter(ds); batch = next(it); state = it.get_state()   # ... it.set_state(state)
  later = iter(training_pipeline(sources, [stats], batch_size=8, seed=0, start=100))  # batch 100 on

Batches are formed before the (optional) worker processes split the work, so batch ``k`` is a
function of ``k`` alone: the same with any ``num_workers``, and a run resumed at step ``k``
continues with ``start=k``.

A batch is a dict of numpy arrays with a leading batch axis: ``frames`` float32
``[B, F, H, W, 3]`` in [-1, 1], ``actions`` float32 ``[B, F-1, A]`` normalised, ``instruction``
bytes ``[B]``, ``episode`` / ``start`` int64 ``[B]``, ``source`` int64 ``[B]`` (mixture member)
and the datasets' extras.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any, Mapping, Sequence

import grain
import ml_collections
import numpy as np

from wmjax.data.latents import open_latent_splits
from wmjax.data.oxe import DatasetSpec
from wmjax.data.rlds import make_window, no_windows_error, window_starts
from wmjax.data.sources import ArrayRecordEpisodes, open_splits
from wmjax.data.stats import ActionStats
from wmjax.frames import to_model

log = logging.getLogger(__name__)


class WindowSource:
  """Random access to every window of ``frames`` frames (stride ``stride``) of an episode source,
  frames fitted to ``resolution`` the way the spec says (``spec.resize``: crop or pad).

  Episodes shorter than ``frames`` (and those without the spec's camera, which have length 0)
  are skipped and counted in ``num_skipped_episodes``; the short ones are logged (the cameraless
  ones were when the source was read). ``only``: the indices of the episodes to read (default
  all).
  """

  def __init__(self, episodes: ArrayRecordEpisodes, frames: int, stride: int,
               resolution: tuple[int, int] | None, only: Sequence[int] | None = None):
    self.episodes, self.frames, self.resolution = episodes, frames, resolution
    lengths = episodes.lengths()
    kept = np.arange(len(lengths)) if only is None else np.unique(np.asarray(only, np.int64))
    if len(kept) and (kept[0] < 0 or kept[-1] >= len(lengths)):
      raise ValueError(f"episode indices must lie in [0, {len(lengths)}) for "
                       f"{episodes.builder_dir} [{episodes.split}], got {kept[0]}..{kept[-1]}")
    lengths = lengths[kept]
    starts = [(e, s) for e, n in zip(kept, lengths) for s in window_starts(int(n), frames, stride)]
    self.index = np.asarray(starts, np.int64).reshape(-1, 2)
    self.num_skipped_episodes = int((lengths < frames).sum())
    short = int(((lengths > 0) & (lengths < frames)).sum())
    if short:
      log.warning("%s [%s]: skipped %d of %d episodes shorter than the %d-frame window "
                  "(data.frames)", episodes.builder_dir, episodes.split, short, len(lengths),
                  frames)
    if len(self.index) == 0:
      raise no_windows_error(f"{episodes.builder_dir} [{episodes.split}]", len(lengths), frames)

  @property
  def spec(self):
    return self.episodes.spec

  def __len__(self) -> int:
    return len(self.index)

  def __getitem__(self, k: int) -> dict[str, Any]:
    episode, start = (int(v) for v in self.index[k])
    steps = self.episodes.episode(episode, start, start + self.frames)
    return make_window(steps, start, self.frames, self.resolution, episode, self.spec.resize)


@dataclasses.dataclass
class Member:
  """One dataset of a run: its spec, action statistics, windows and mixture weight, and the shape
  of one of its frames as read (``(H, W, 3)`` RGB, or pre-encoded ``latents``' own shape)."""

  spec: DatasetSpec
  stats: ActionStats
  train: WindowSource
  eval: WindowSource | None  # None when the run does not evaluate (``train.eval_every=0``)
  weight: float
  frame_shape: tuple[int, ...]
  latents: bool


def member_configs(data: ml_collections.ConfigDict) -> list[ml_collections.ConfigDict]:
  """``config.data`` itself, or one config per ``data.mixture`` entry (a member inherits what its
  entry leaves None from ``config.data``)."""
  if not data.mixture:
    return [data]
  # a dataset's own reading (spec, camera) is not inherited by the others
  base = {k: v for k, v in data.to_dict().items() if k not in ("mixture", "spec", "image_key")}
  members = []
  for name, entry in data.mixture.items():
    own = {k: v for k, v in entry.to_dict().items() if v is not None}
    members.append(ml_collections.ConfigDict(dict(base, dataset=name, **own),
                                             type_safe=False))
  return members


def open_members(data: ml_collections.ConfigDict, codec: Mapping | None,
                 evaluation: bool = True) -> list[Member]:
  """Every dataset of ``config.data`` (one, or each ``mixture`` member: see
  :func:`member_configs`) as a run reads it: windows of ``data.frames`` frames
  of its training split and, with ``evaluation``, of its evaluation split, and the training
  split's statistics. Pre-encoded latents (``latents_dir``) must have been encoded with
  ``codec`` (``config.codec``); a mixture is all latents or all frames."""
  members = []
  for member in member_configs(data):
    latents = bool(member.latents_dir)
    splits = (open_latent_splits(member, codec, evaluation) if latents
              else open_splits(member, evaluation))
    members.append(Member(
        splits.train.spec, splits.stats,
        WindowSource(splits.train, data.frames, member.train_stride, splits.resolution),
        WindowSource(splits.eval, data.frames, member.eval_stride, splits.resolution)
        if evaluation else None,
        float(member.get("weight", 1.0)), splits.frame_shape, latents))
  if len({m.latents for m in members}) > 1:
    raise ValueError("a mixture must be all pre-encoded latents or all frames")
  return members


STANDARD_KEYS = ("frames", "actions", "instruction", "episode", "start")


class Normalize:
  """Normalise a window's actions with its dataset's statistics, zero-pad them to ``action_dim``
  and tag the mixture member. Dataset-specific extras are dropped unless ``keep_extras``
  (mixtures keep only the keys every dataset has)."""

  def __init__(self, stats: ActionStats, mode: str, action_dim: int, source_id: int,
               keep_extras: bool = True):
    self.stats, self.mode, self.action_dim, self.source_id = stats, mode, action_dim, source_id
    self.keep_extras = keep_extras

  def __call__(self, window: dict[str, Any]) -> dict[str, Any]:
    out = dict(window) if self.keep_extras else {k: window[k] for k in STANDARD_KEYS}
    out["actions"] = self.stats.normalize(window["actions"], self.mode, pad_to=self.action_dim)
    out["source"] = np.int64(self.source_id)
    return out


def frames_to_float(batch: dict[str, Any]) -> dict[str, Any]:
  """uint8 frames -> float32 in [-1, 1] (done last, after workers, to move 4x fewer bytes);
  pre-encoded latents (float16) -> float32."""
  return dict(batch, frames=to_model(batch["frames"]))


def _ignore_interrupts(worker_index: int, worker_count: int) -> None:
  """Data workers leave Ctrl-C to the process that reads from them (a terminal sends it to the
  whole process group), which then stops them itself after saving its checkpoint."""
  del worker_index, worker_count
  import signal
  signal.signal(signal.SIGINT, signal.SIG_IGN)


def _check_compatible(sources: Sequence[WindowSource], action_dim: int) -> None:
  shapes = {(s.frames, s.resolution) for s in sources}
  if len(shapes) > 1:
    raise ValueError(f"mixed datasets must share frames and resolution, got {sorted(shapes)}")
  for s in sources:
    if s.spec.action_dim > action_dim:
      raise ValueError(f"{s.spec.name} has {s.spec.action_dim}-dim actions, more than the "
                       f"pipeline's action_dim={action_dim}")


def training_pipeline(sources: Sequence[WindowSource], stats: Sequence[ActionStats], *,
                      batch_size: int, seed: int = 0, weights: Sequence[float] | None = None,
                      shuffle: bool = True, repeat: bool = True, normalization: str = "mean_std",
                      action_dim: int | None = None, shard_index: int | None = None,
                      shard_count: int | None = None, num_workers: int = 0,
                      drop_remainder: bool = True, start: int = 0) -> grain.IterDataset:
  """Batches of this process's shard of a (weighted) mixture of window sources.

  Each source is sharded by process (``shard_index::shard_count``, default the JAX process),
  shuffled deterministically (reshuffled every epoch) and repeated, then sources are mixed by
  ``weights`` (a mixture keeps only the standard keys). ``batch_size`` is per process. The
  batches are formed on the random-access dataset, before ``num_workers`` processes split them
  between themselves, so the sequence does not depend on ``num_workers``; ``start`` skips to batch
  ``start`` at no cost (how a resumed run continues). Iterators of the result have
  ``get_state`` / ``set_state``.
  """
  if not sources:
    raise ValueError("training_pipeline needs at least one source")
  if len(stats) != len(sources):
    raise ValueError(f"got {len(stats)} action statistics for {len(sources)} sources")
  if weights is not None and len(weights) != len(sources):
    raise ValueError(f"got {len(weights)} mixture weights for {len(sources)} sources")
  if shard_index is None or shard_count is None:
    import jax
    shard_index, shard_count = jax.process_index(), jax.process_count()
  if not 0 <= shard_index < shard_count:
    raise ValueError(f"shard_index must be in [0, {shard_count}), got {shard_index}")
  if start < 0:
    raise ValueError(f"start must be a batch index >= 0, got {start}")
  action_dim = action_dim or max(s.spec.action_dim for s in sources)
  _check_compatible(sources, action_dim)

  members = []
  for i, (source, source_stats) in enumerate(zip(sources, stats)):
    ds = grain.MapDataset.source(source)[shard_index::shard_count]
    if shuffle:
      ds = ds.shuffle(seed=seed + i)
    if repeat:
      ds = ds.repeat()
    members.append(ds.map(Normalize(source_stats, normalization, action_dim, i,
                                    keep_extras=len(sources) == 1)))
  mixed = members[0] if len(members) == 1 else grain.MapDataset.mix(members, weights)
  batches = mixed.batch(batch_size, drop_remainder=drop_remainder)[start:]
  # Threads prefetch whole batches; the buffer holds about as many windows as grain's default.
  buffered = max(2, min(64, 512 // batch_size))
  batched = batches.to_iter_dataset(grain.ReadOptions(num_threads=min(16, buffered),
                                                      prefetch_buffer_size=buffered))
  if num_workers > 0:
    from absl import flags
    if not flags.FLAGS.is_parsed():
      flags.FLAGS.mark_as_parsed()  # grain workers read absl flags
    batched = batched.mp_prefetch(grain.MultiprocessingOptions(num_workers=num_workers),
                                  worker_init_fn=_ignore_interrupts)
  return batched.map(frames_to_float)
