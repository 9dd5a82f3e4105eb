"""Reading RLDS episodes from a TFDS builder directory, by either of two paths.

* :class:`ArrayRecordEpisodes` — random access over an ArrayRecord split (``tfds`` data source,
  no TensorFlow), the path grain uses.
* :func:`tfrecord_episodes` — streaming a TFRecord split with ``tf.data`` (the published Open-X
  files, local or ``gs://gresearch/robotics/...``); needs the ``[tf]`` extra.

Both yield :class:`wmjax.data.rlds.Episode` objects with encoded images, so the windows they make
are identical, and both skip (or refuse) episodes without the spec's camera. Derived files
(episode lengths and camera flags per split, action statistics per split and spec) are cached
beside the data, or under ``~/.cache/wmjax`` when the data directory is not writable (e.g. a
``gs://`` bucket).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
from typing import Any, Iterable, Iterator, Mapping, Sequence, Union

import ml_collections
import numpy as np
import tensorflow_datasets as tfds

from wmjax import registry
from wmjax.data import oxe, synthetic
from wmjax.data.rlds import Episode, stack_steps
from wmjax.data.stats import ActionStats

log = logging.getLogger(__name__)


def open_builder(builder_dir: str):
  """``tfds.builder_from_directory`` with a clear error when the directory holds no dataset:
  the ``wmjax data import`` command when it holds a raw LeRobot, IRASim or WPE dataset."""
  try:
    return tfds.builder_from_directory(os.fspath(builder_dir))
  except Exception as e:  # tfds raises several types for a missing / malformed directory
    hint = _import_hint(os.fspath(builder_dir))
    raise ValueError(f"no TFDS dataset at {builder_dir!r} " + (hint or (
        f"(expected dataset_info.json and features.json of a prepared dataset): {e}"))) from e


def _import_hint(path: str) -> str | None:
  """How to import the raw dataset at ``path``, or None when it holds none that wmjax imports."""
  from wmjax.data import irasim, lerobot, wpe
  for command, name, module in (("lerobot", "LeRobot", lerobot), ("irasim", "IRASim", irasim),
                                ("wpe", "WPE", wpe)):
    if module.recognises(path):
      return (f"but a raw {name} dataset: import it first with `wmjax data import {command} "
              f"{path} OUT_DIR`, then use OUT_DIR")
  return None


def check_shards(builder, builder_dir: str, split: str | None = None) -> None:
  """ValueError naming the first shard of ``split`` (default: every split) that does not hold
  the episodes ``dataset_info.json`` counts in it: missing, empty, or (ArrayRecord, whose footer
  says how many records it has) unreadable or holding another number. TFRecord shards are
  checked by size only (counting their records means reading them whole); shards in a bucket
  (``gs://``) are not checked."""
  if "://" in os.fspath(builder_dir):
    return
  splits = [builder.info.splits[split]] if split else builder.info.splits.values()
  for info in splits:
    for path, expected in zip(info.filepaths, info.shard_lengths):
      problem = _shard_problem(os.fspath(path), builder.info.file_format.value, expected)
      if problem:
        raise ValueError(f"{path} {problem}, but dataset_info.json counts {expected} episodes "
                         f"in it: the dataset is damaged; copy, convert or import it again")


def _shard_problem(path: str, file_format: str, expected: int) -> str | None:
  """What keeps a shard from holding its ``expected`` episodes, or None."""
  if not expected:
    return None
  if not os.path.exists(path):
    return "is missing"
  if not os.path.getsize(path):
    return "is empty (0 bytes)"
  if file_format != "array_record":
    return None
  from array_record.python import array_record_module
  reader = array_record_module.ArrayRecordReader(path, "readahead_buffer_size:0,max_parallelism:0")
  if not reader.ok():  # nothing to close (closing it raises)
    return "is not a readable ArrayRecord file (truncated or corrupted)"
  count = reader.num_records()
  reader.close()
  return None if count == expected else f"holds {count} episodes"


SpecArg = Union[str, oxe.DatasetSpec, Sequence[oxe.DatasetSpec], None]


def resolve(builder, spec: SpecArg = None) -> oxe.DatasetSpec:
  """The spec of ``builder``'s data: ``spec`` is a dataset name (its built-in layouts), a spec, a
  sequence of candidate specs (:func:`wmjax.data.oxe.specs_from_config`), or None (the
  builder's own name)."""
  return oxe.resolve_spec(spec or builder.info.name, builder.info.features)


def skip_image_decoding(spec: oxe.DatasetSpec) -> dict[str, Any]:
  """TFDS ``decoders`` that leave the spec's image features encoded (nested like the features)."""
  decoders: dict[str, Any] = {}
  for key in spec.image_keys:
    *parents, leaf = ("steps/" + key).split("/")
    node = decoders
    for part in parents:
      node = node.setdefault(part, {})
    node[leaf] = tfds.decode.SkipDecoding()
  return decoders


def _split_name(split: str) -> str:
  """``train[:95%]`` -> ``train___95__`` (file names)."""
  return re.sub(r"[^\w.-]", "_", split)


def _cache_candidates(builder_dir: str, filename: str) -> list[str]:
  local = builder_dir if "://" not in builder_dir else None
  digest = hashlib.sha1(os.path.abspath(builder_dir).encode()).hexdigest()[:16]
  fallback = os.path.join(os.path.expanduser("~/.cache/wmjax"), digest, filename)
  return ([os.path.join(local, filename)] if local else []) + [fallback]


def read_cached_json(builder_dir: str, filename: str) -> Any | None:
  for path in _cache_candidates(builder_dir, filename):
    if os.path.exists(path):
      with open(path) as f:
        return json.load(f)
  return None


def write_cached_json(builder_dir: str, filename: str, data: Any) -> str:
  """Write beside the data if possible, else to the user cache; atomic. Returns the path."""
  for path in _cache_candidates(builder_dir, filename):
    try:
      os.makedirs(os.path.dirname(path), exist_ok=True)
      tmp = f"{path}.tmp-{os.getpid()}"
      with open(tmp, "w") as f:
        json.dump(data, f)
      os.replace(tmp, path)
      return path
    except OSError:
      continue
  raise OSError(f"cannot write {filename} beside {builder_dir} nor in ~/.cache/wmjax")


_SLICE = re.compile(r"^([\w-]+)\[(-?\d+%?)?:(-?\d+%?)?\]$")


def episode_split(split: str, num_episodes: int) -> str:
  """``split`` with its percent boundaries as episode indices, rounded as TFDS rounds them but
  kept off the ends: of two or more episodes, ``train[:90%]`` keeps at least one and
  ``train[90%:]`` holds at least one out (TFDS gives 3 episodes' ``train[90%:]`` none). Other
  splits are returned as they are.

  >>> episode_split("train[90%:]", 3), episode_split("train[:90%]", 3)
  ('train[2:]', 'train[:2]')
  """
  match = _SLICE.match(split)
  if not match or "%" not in split:
    return split

  def index(bound: str | None) -> str:
    if bound is None or not bound.endswith("%"):
      return bound or ""
    percent = int(bound[:-1]) % 100 if int(bound[:-1]) < 0 else int(bound[:-1])
    if percent <= 0 or percent >= 100 or num_episodes < 2:
      return str(round(num_episodes * min(max(percent, 0), 100) / 100))
    return str(min(max(round(num_episodes * percent / 100), 1), num_episodes - 1))

  base, start, stop = match.groups()
  return f"{base}[{index(start)}:{index(stop)}]"


def _check_split(builder, builder_dir: str, split: str) -> str:
  """The split as TFDS is asked for it (:func:`episode_split`), or an error naming the splits."""
  base = split.split("[")[0]
  if base not in builder.info.splits:  # slices like "train[95%:]" are fine
    raise ValueError(f"{builder_dir} has no split {split!r}; splits: {list(builder.info.splits)}")
  return episode_split(split, builder.info.splits[base].num_examples)


def _missing_camera(spec: oxe.DatasetSpec, flags: Mapping[str, Any], where: str) -> bool:
  """Whether an episode lacks one of the spec's cameras (its ``image_flags`` say so); with
  ``missing_image='error'`` that is an error."""
  missing = [key for key in spec.image_flags if not bool(np.asarray(flags[key]))]
  if missing and spec.missing_image == "error":
    raise ValueError(f"{where} lacks the camera {list(spec.image_keys)} ({', '.join(missing)} "
                     f"is false); choose another with data.image_key, or skip such episodes "
                     f"with data.missing_image='skip'")
  return bool(missing)


def _log_skipped(where: str, spec: oxe.DatasetSpec, skipped: int, total: int) -> None:
  if skipped:
    log.warning("%s: skipped %d of %d episodes without the camera %s (%s false)", where, skipped,
                total, list(spec.image_keys), ", ".join(spec.image_flags))


class ArrayRecordEpisodes:
  """Random access to the episodes of an ArrayRecord RLDS split, images left encoded.

  Steps and lengths are counted after the spec's ``frame_step`` subsampling. Episodes without
  the spec's camera (see :class:`wmjax.data.oxe.DatasetSpec`) have length 0 in :meth:`lengths`,
  so no window and no statistic comes from them; how many were skipped is logged.
  Picklable (it reopens the data source lazily), so grain worker processes can use it.
  """

  def __init__(self, builder_dir: str, split: str, spec: SpecArg = None):
    builder = open_builder(builder_dir)
    if builder.info.file_format.value != "array_record":
      raise ValueError(f"{builder_dir} is stored as {builder.info.file_format.value}; random access "
                       f"needs ArrayRecord: run `wmjax data convert {builder_dir} OUT_DIR`")
    self._tfds_split = _check_split(builder, builder_dir, split)
    check_shards(builder, builder_dir, split.split("[")[0])
    self.builder_dir, self.split = os.fspath(builder_dir), split
    self.spec = resolve(builder, spec)
    self._length = builder.info.splits[self._tfds_split].num_examples
    if not self._length:
      base = split.split("[")[0]
      total = builder.info.splits[base].num_examples
      fix = (f"with one episode train and evaluate on it: data.train_split={base!r} and "
             f"data.eval_split={base!r}" if total == 1 else
             f"with few episodes name them, e.g. data.train_split='{base}[:-1]' and "
             f"data.eval_split='{base}[-1:]'")
      raise ValueError(f"the split {split!r} of {builder_dir} is empty ({total} episodes in "
                       f"{base!r}); {fix}")
    self._flag_keys = [k for k, f in oxe.feature_leaves(builder.info.features).items()
                       if k.startswith("episode_metadata/has_") and np.dtype(f.np_dtype) == bool]
    self._source = None
    self._lengths = None

  def __getstate__(self):
    return dict(self.__dict__, _source=None)

  def __len__(self) -> int:
    return self._length

  def _record(self, index: int):
    if self._source is None:
      builder = open_builder(self.builder_dir)
      self._source = builder.as_data_source(split=self._tfds_split,
                                            decoders=skip_image_decoding(self.spec))
    return self._source[index]

  def episode(self, index: int, start: int = 0, stop: int | None = None) -> Episode:
    """Episode ``index``, optionally only its (subsampled) steps ``[start, stop)``."""
    steps = self._record(index)["steps"]
    k = self.spec.frame_step
    stop = len(steps) if stop is None else min(stop * k, len(steps))
    return Episode.from_steps(self.spec, stack_steps([steps[i] for i in range(start * k, stop)]),
                              start, index)

  def _index(self) -> dict:
    """Raw lengths and ``episode_metadata/has_*`` flags of every episode, read once and cached
    as JSON."""
    filename = f"wmjax_episodes-{_split_name(self.split)}.json"
    cached = read_cached_json(self.builder_dir, filename)
    if (not isinstance(cached, dict) or cached.get("split") != self.split
        or len(cached["lengths"]) != len(self)):
      records = (self._record(i) for i in range(len(self)))
      index = {"split": self.split, "lengths": [], "flags": {k: [] for k in self._flag_keys}}
      for record in records:
        index["lengths"].append(len(record["steps"]))
        for key in self._flag_keys:
          index["flags"][key].append(bool(oxe.get_path(record, key)))
      cached = index
      write_cached_json(self.builder_dir, filename, cached)
    return cached

  def lengths(self) -> np.ndarray:
    """Number of (subsampled) steps of every episode; 0 for those without the spec's camera."""
    if self._lengths is None:
      index = self._index()
      k = self.spec.frame_step
      lengths = -(-np.asarray(index["lengths"], np.int64) // k)
      where = f"{self.builder_dir} [{self.split}]"
      missing = np.asarray([_missing_camera(self.spec, {key: index["flags"][key][e]
                                                        for key in self.spec.image_flags},
                                            f"{where} episode {e}")
                            for e in range(len(lengths))], bool)
      _log_skipped(where, self.spec, int(missing.sum()), len(lengths))
      self._lengths = np.where(missing, 0, lengths)
    return self._lengths

  def with_camera(self) -> Iterator[Episode]:
    """Every episode that has the spec's camera, in order (read as they are iterated)."""
    for index, length in enumerate(self.lengths()):
      if length > 0:
        yield self.episode(index)

  def action_stats(self) -> ActionStats:
    """The action statistics of this split (as :func:`action_stats` computes and caches them),
    read from these episodes."""
    return _cached_stats(self.builder_dir, self.split, self.spec, self.with_camera())


def tfrecord_episodes(builder_dir: str, split: str, spec: SpecArg = None,
                      shuffle_files: bool = False) -> Iterator[Episode]:
  """Stream the episodes of a TFRecord RLDS split with tf.data, in file order (ArrayRecord is
  read by :class:`ArrayRecordEpisodes`; :func:`read_episodes` picks the path). Episodes without
  the spec's camera are skipped (counted in the log) or an error, as in
  :class:`ArrayRecordEpisodes`."""
  builder = open_builder(builder_dir)
  if builder.info.file_format.value != "tfrecord":
    raise ValueError(f"{builder_dir} is stored as {builder.info.file_format.value}; tf.data reads "
                     f"TFRecord only: read it with ArrayRecordEpisodes (or read_episodes)")
  tfds_split = _check_split(builder, builder_dir, split)
  check_shards(builder, builder_dir, split.split("[")[0])
  try:
    import tensorflow as tf
  except ImportError as e:
    raise ImportError("the tf.data path needs TensorFlow: pip install 'wmjax[tf]'") from e
  spec = resolve(builder, spec)
  ds = builder.as_dataset(split=tfds_split, decoders=skip_image_decoding(spec),
                          shuffle_files=shuffle_files)

  def batch_steps(episode):
    steps = tf.data.Dataset.get_single_element(episode["steps"].batch(2 ** 31 - 1))
    return steps, {key: oxe.get_path(episode, key) for key in spec.image_flags}

  ds = ds.map(batch_steps, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
  where = f"{builder_dir} [{split}]"
  skipped = total = 0
  for index, (steps, flags) in enumerate(tfds.as_numpy(ds)):
    total += 1
    if _missing_camera(spec, flags, f"{where} episode {index}"):
      skipped += 1
      continue
    yield Episode.from_steps(spec, steps, index=index)
  _log_skipped(where, spec, skipped, total)


def read_episodes(builder_dir: str, split: str, spec: SpecArg = None) -> Iterator[Episode]:
  """Every episode of a split that has the spec's camera, in order, by the path its file format
  needs (ArrayRecord: random access; TFRecord: tf.data), opened when first iterated."""
  if open_builder(builder_dir).info.file_format.value == "array_record":
    yield from ArrayRecordEpisodes(builder_dir, split, spec).with_camera()
  else:
    yield from tfrecord_episodes(builder_dir, split, spec)


def stats_filename(split: str, spec: oxe.DatasetSpec) -> str:
  """Statistics are cached per split and spec (``train[:2]`` never reads ``train``'s)."""
  key = hashlib.sha1(f"{split}|{spec.digest()}".encode()).hexdigest()[:12]
  return f"wmjax_action_stats-{_split_name(split)}-{key}.json"


def action_stats(builder_dir: str, split: str = "train", spec: SpecArg = None,
                 recompute: bool = False) -> ActionStats:
  """The action statistics of exactly the episodes of ``split`` (e.g. ``train[:95%]``) read with
  ``spec``, computed on first use and cached as JSON beside the data (:func:`stats_filename`)."""
  builder = open_builder(builder_dir)
  _check_split(builder, builder_dir, split)
  resolved = resolve(builder, spec)
  return _cached_stats(builder_dir, split, resolved, read_episodes(builder_dir, split, resolved),
                       recompute)


def _cached_stats(builder_dir: str, split: str, spec: oxe.DatasetSpec,
                  episodes: Iterable[Episode], recompute: bool = False) -> ActionStats:
  """The statistics of ``split`` read with the resolved ``spec`` from their cache
  (:func:`stats_filename`), else computed from its ``episodes`` (those with the spec's camera, a
  lazy iterable: not read when the cache answers) and cached."""
  filename = stats_filename(split, spec)
  cached = None if recompute else read_cached_json(builder_dir, filename)
  if cached is not None:
    return ActionStats.from_dict(cached)
  # The last step's action leads nowhere and never enters a window.
  actions = [e.actions[:-1] for e in episodes]
  if not actions:
    raise ValueError(f"{builder_dir} [{split}] has no episode to compute action statistics from")
  stats = ActionStats.compute(np.concatenate(actions), spec.name, spec.gripper_dim)
  write_cached_json(builder_dir, filename, dict(stats.to_dict(), split=split,
                                                spec=spec.to_dict()))
  return stats


def dataset_dir(data: ml_collections.ConfigDict) -> str:
  """The ArrayRecord builder directory of a data config (``config.data`` or a mixture member):
  ``builder_dir``, or for a dataset a task generates (:func:`wmjax.registry.generated_datasets`)
  ``data_dir``, where it is generated if missing with the parameters in
  ``config.data.<dataset>``."""
  generated = registry.generated_datasets().get(data.dataset)
  if generated is not None:
    for key in ("train_split", "eval_split"):  # before minutes of generating it
      split = data.get(key) or ""
      if split and split.split("[")[0] not in synthetic.SPLITS:
        raise ValueError(f"config.data.{key}={split!r}: the generated {data.dataset} dataset has "
                         f"the splits {list(synthetic.SPLITS)} (slices like 'train[:90%]' too)")
    params = generated.params.from_dict(data.get(data.dataset, {}))
    return generated.prepare(os.path.expanduser(data.data_dir), params)
  oxe.specs_from_config(data)  # an unknown dataset without a spec fails here, clearly
  if not data.get("builder_dir"):
    raise ValueError(f"config.data.builder_dir must point at the ArrayRecord builder directory "
                     f"of {data.dataset} (see `wmjax data convert`)")
  return os.path.expanduser(data.builder_dir)


@dataclasses.dataclass(frozen=True)
class ConfiguredDataset:
  """The dataset a data config names (``config.data`` or a mixture member), found (generated if
  need be): its builder directory and the specs to read it with."""

  data: ml_collections.ConfigDict
  builder_dir: str
  specs: Sequence[oxe.DatasetSpec]

  def split(self, name: str) -> ArrayRecordEpisodes:
    """The episodes of split ``name`` (e.g. ``test`` or ``train[:95%]``)."""
    return ArrayRecordEpisodes(self.builder_dir, name, self.specs)

  def train_stats(self) -> ActionStats:
    """The action statistics of the training split (what the model normalises with)."""
    return action_stats(self.builder_dir, self.data.train_split, self.specs)

  def resolution(self, spec: oxe.DatasetSpec) -> tuple[int, int]:
    """``(H, W)`` the frames are read at: ``data.resolution``, else the spec's own."""
    return tuple(self.data.resolution or spec.resolution)


def open_dataset(data: ml_collections.ConfigDict) -> ConfiguredDataset:
  """The dataset of a data config (see :func:`dataset_dir` and
  :func:`wmjax.data.oxe.specs_from_config`)."""
  return ConfiguredDataset(data, dataset_dir(data), oxe.specs_from_config(data))


@dataclasses.dataclass(frozen=True)
class Splits:
  """What a run reads of one dataset: the episodes of its training split and (where the run
  evaluates) of its evaluation split, the training split's action statistics, the resolution
  ``(H, W)`` its frames are read at and the shape of one frame as read (``(H, W, 3)`` RGB, or the
  pre-encoded latents' shape; their episodes are :class:`wmjax.data.latents.LatentEpisodes`, read
  alike)."""

  train: ArrayRecordEpisodes
  eval: ArrayRecordEpisodes | None
  stats: ActionStats
  resolution: tuple[int, int]
  frame_shape: tuple[int, ...]


def open_splits(data: ml_collections.ConfigDict, evaluation: bool = True) -> Splits:
  """The :class:`Splits` of the dataset a data config names (:func:`open_dataset`):
  ``data.train_split``, and ``data.eval_split`` with ``evaluation``."""
  dataset = open_dataset(data)
  train = dataset.split(data.train_split)
  held_out = dataset.split(data.eval_split) if evaluation else None
  resolution = dataset.resolution(train.spec)
  return Splits(train, held_out, train.action_stats(), resolution, resolution + (3,))
