"""Reading RLDS episodes from a TFDS builder directory, by either of two paths.

* :class:`ArrayRecordEpisodes` — random access over an ArrayRecord split (``tfds`` data source,
  no TensorFlow), the path grain uses.
* :func:`tfrecord_episodes` — streaming a TFRecord split with ``tf.data`` (the published Open-X
  files, local or ``gs://gresearch/robotics/...``); needs the ``[tf]`` extra.

Both yield :class:`wmjax.data.rlds.Episode` objects with encoded images, so the windows they make
are identical. Derived files (episode lengths, action statistics) are cached beside the data, or
under ``~/.cache/wmjax`` when the data directory is not writable (e.g. a ``gs://`` bucket).
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import Any, Iterator

import ml_collections
import numpy as np
import tensorflow_datasets as tfds

from wmjax.data import gridworld, oxe, pusht
from wmjax.data.rlds import Episode, skip_image_decoding, stack_steps
from wmjax.data.stats import STATS_FILE, ActionStats


def open_builder(builder_dir: str):
  """``tfds.builder_from_directory`` with a clear error when the directory holds no dataset."""
  try:
    return tfds.builder_from_directory(os.fspath(builder_dir))
  except Exception as e:  # tfds raises several types for a missing / malformed directory
    raise ValueError(f"no TFDS dataset at {builder_dir!r} (expected dataset_info.json and "
                     f"features.json of a prepared dataset): {e}") from e


def resolve(builder, name: str | None = None) -> oxe.DatasetSpec:
  return oxe.resolve_spec(name or builder.info.name, builder.info.features)


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


class ArrayRecordEpisodes:
  """Random access to the episodes of an ArrayRecord RLDS split, images left encoded.

  Picklable (it reopens the data source lazily), so grain worker processes can use it.
  """

  def __init__(self, builder_dir: str, split: str, name: str | None = None):
    builder = open_builder(builder_dir)
    if builder.info.file_format.value != "array_record":
      raise ValueError(f"{builder_dir} is stored as {builder.info.file_format.value}; random access "
                       f"needs ArrayRecord: run `wmjax data convert {builder_dir} OUT_DIR`")
    if split.split("[")[0] not in builder.info.splits:  # slices like "train[95%:]" are fine
      raise ValueError(f"{builder_dir} has no split {split!r}; splits: {list(builder.info.splits)}")
    self.builder_dir, self.split = os.fspath(builder_dir), split
    self.spec = resolve(builder, name)
    self._length = builder.info.splits[split].num_examples
    self._source = None

  def __getstate__(self):
    return dict(self.__dict__, _source=None)

  def __len__(self) -> int:
    return self._length

  def _steps(self, index: int):
    if self._source is None:
      builder = open_builder(self.builder_dir)
      self._source = builder.as_data_source(split=self.split,
                                            decoders=skip_image_decoding(self.spec))
    return self._source[index]["steps"]

  def episode(self, index: int, start: int = 0, stop: int | None = None) -> Episode:
    """Episode ``index``, optionally only its steps ``[start, stop)``."""
    steps = self._steps(index)
    stop = len(steps) if stop is None else stop
    return Episode.from_steps(self.spec, stack_steps([steps[i] for i in range(start, stop)]), start)

  def lengths(self) -> np.ndarray:
    """Number of steps of every episode (read once, then cached as JSON)."""
    filename = f"wmjax_lengths-{self.split}.json"
    cached = read_cached_json(self.builder_dir, filename)
    if cached is None or len(cached) != len(self):
      cached = [len(self._steps(i)) for i in range(len(self))]
      write_cached_json(self.builder_dir, filename, cached)
    return np.asarray(cached, np.int64)


def tfrecord_episodes(builder_dir: str, split: str, name: str | None = None,
                      shuffle_files: bool = False) -> Iterator[Episode]:
  """Stream the episodes of a TFRecord (or ArrayRecord) RLDS split with tf.data, in file order."""
  try:
    import tensorflow as tf
  except ImportError as e:
    raise ImportError("the tf.data path needs TensorFlow: pip install 'wmjax[tf]'") from e
  builder = open_builder(builder_dir)
  spec = resolve(builder, name)
  ds = builder.as_dataset(split=split, decoders=skip_image_decoding(spec),
                          shuffle_files=shuffle_files)
  ds = ds.map(lambda episode: tf.data.Dataset.get_single_element(
      episode["steps"].batch(2 ** 31 - 1)), num_parallel_calls=tf.data.AUTOTUNE,
              deterministic=True)
  for steps in tfds.as_numpy(ds):
    yield Episode.from_steps(spec, steps)


def action_stats(builder_dir: str, split: str = "train", name: str | None = None,
                 recompute: bool = False) -> ActionStats:
  """The split's action statistics, computed on first use and cached as JSON beside the data."""
  cached = None if recompute else read_cached_json(builder_dir, STATS_FILE)
  if cached is not None:
    return ActionStats.from_dict(cached)
  builder = open_builder(builder_dir)
  spec = resolve(builder, name)
  if builder.info.file_format.value == "array_record":
    source = ArrayRecordEpisodes(builder_dir, split, name)
    episodes = (source.episode(i) for i in range(len(source)))
  else:
    episodes = tfrecord_episodes(builder_dir, split, name)
  # The last step's action leads nowhere and never enters a window.
  actions = [e.actions[:-1] for e in episodes]
  stats = ActionStats.compute(np.concatenate(actions), spec.name, spec.gripper_dim)
  write_cached_json(builder_dir, STATS_FILE, stats.to_dict())
  return stats


# Datasets wmjax generates itself: name -> (parameter dataclass, prepare(data_dir, params)).
GENERATED = {"gridworld": (gridworld.GridworldConfig, gridworld.prepare),
             "pusht": (pusht.PushTConfig, pusht.prepare)}


def dataset_dir(data: ml_collections.ConfigDict) -> str:
  """The ArrayRecord builder directory of a data config (``config.data`` or a mixture member):
  ``builder_dir``, or for a generated dataset (gridworld, Push-T) ``data_dir``, where it is
  generated if missing with the parameters in ``config.data.<dataset>``."""
  if data.dataset in GENERATED:
    params_class, prepare = GENERATED[data.dataset]
    params = params_class(**data.get(data.dataset, {}))
    return prepare(os.path.expanduser(data.data_dir), params)
  if data.dataset not in oxe.SPECS:
    raise ValueError(f"unknown dataset {data.dataset!r}; known: {sorted(oxe.SPECS)}")
  if not data.get("builder_dir"):
    raise ValueError(f"config.data.builder_dir must point at the ArrayRecord builder directory "
                     f"of {data.dataset} (see `wmjax data convert`)")
  return os.path.expanduser(data.builder_dir)
