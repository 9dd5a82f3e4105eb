"""A TFDS RLDS builder for datasets wmjax generates itself (gridworld, Push-T), in ArrayRecord.

A subclass names its parameters (a frozen dataclass with ``name``, ``seed``, ``image_size``,
``train_episodes`` and ``test_episodes``), its action dimension, the per-step observation extras
and the episode generator; this class writes the standard RLDS layout
(``steps/observation/image`` as PNG, ``steps/action``, ``language_instruction``, ``reward``,
``discount``, ``is_first`` / ``is_last`` / ``is_terminal``) with one builder config per parameter
set, so every variant lives in its own directory and is written once.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import os
from typing import Any, Iterator

import numpy as np
import tensorflow_datasets as tfds

from wmjax.data.writer import png


@dataclasses.dataclass
class GeneratedEpisode:
  """``images [L, H, W, 3]`` uint8, ``actions [L, A]`` (step ``t``'s action leads to frame
  ``t + 1``; the last one is never used), ``rewards [L]``, per-step ``observations`` extras."""

  images: np.ndarray
  actions: np.ndarray
  instruction: str
  rewards: np.ndarray
  observations: dict[str, np.ndarray]


class SyntheticBuilder(tfds.core.GeneratorBasedBuilder):
  """Base builder; subclasses set ``VERSION`` / ``RELEASE_NOTES`` and implement the hooks."""

  SPLIT_SEED_OFFSETS = {"train": 0, "test": 1_000_003}

  def __init__(self, *, params, **kwargs):
    self.params = params
    super().__init__(config=tfds.core.BuilderConfig(name=params.name), **kwargs)

  # ---------------------------------------------------------------- abstract: every subclass
  def action_dim(self) -> int:
    raise NotImplementedError(f"{type(self).__name__} must define action_dim()")

  def observation_features(self) -> dict[str, Any]:
    """Per-step ``observation/<name>`` features besides the image."""
    raise NotImplementedError(f"{type(self).__name__} must define observation_features()")

  def episodes(self, count: int, rng: np.random.Generator) -> Iterator[GeneratedEpisode]:
    """``count`` episodes drawn with ``rng``."""
    raise NotImplementedError(f"{type(self).__name__} must define episodes()")

  # ---------------------------------------------------------------- TFDS
  def _info(self) -> tfds.core.DatasetInfo:
    size = self.params.image_size
    step = {
        "observation": {
            "image": tfds.features.Image(shape=(size, size, 3), encoding_format="png"),
            **self.observation_features(),
        },
        "action": tfds.features.Tensor(shape=(self.action_dim(),), dtype=np.float32),
        "language_instruction": tfds.features.Text(),
        "reward": tfds.features.Scalar(dtype=np.float32),
        "discount": tfds.features.Scalar(dtype=np.float32),
        "is_first": np.bool_, "is_last": np.bool_, "is_terminal": np.bool_,
    }
    return tfds.core.DatasetInfo(
        builder=self, description=type(self).__doc__,
        features=tfds.features.FeaturesDict({
            "steps": tfds.features.Dataset(step),
            "episode_metadata": {"episode_id": np.int64},
        }),
        metadata=tfds.core.MetadataDict(dataclasses.asdict(self.params)))

  def _split_generators(self, dl_manager):
    return {split: self._generate_examples(split) for split in self.SPLIT_SEED_OFFSETS}

  def _generate_examples(self, split: str):
    rng = np.random.default_rng(self.params.seed + self.SPLIT_SEED_OFFSETS[split])
    count = self.params.train_episodes if split == "train" else self.params.test_episodes
    for index, episode in enumerate(self.episodes(count, rng)):
      last = len(episode.images) - 1
      steps = [{
          "observation": {"image": png(episode.images[t]),
                          **{k: v[t] for k, v in episode.observations.items()}},
          "action": episode.actions[t], "language_instruction": episode.instruction,
          "reward": episode.rewards[t], "discount": 1.0,
          "is_first": t == 0, "is_last": t == last, "is_terminal": False,
      } for t in range(len(episode.images))]
      yield index, {"steps": steps, "episode_metadata": {"episode_id": index}}


@contextlib.contextmanager
def _one_writer(data_dir: str, name: str):
  """Hold an exclusive lock on ``data_dir/.NAME.lock`` (local directories only), so that jobs
  started together on one machine prepare a dataset once: the others wait, then find it."""
  if "://" in data_dir:
    yield
    return
  os.makedirs(data_dir, exist_ok=True)
  with open(os.path.join(data_dir, f".{name}.lock"), "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    try:
      yield
    finally:
      fcntl.flock(lock, fcntl.LOCK_UN)


def prepare(builder_class: type[SyntheticBuilder], data_dir: str, params) -> str:
  """Write the dataset as ArrayRecord under ``data_dir`` (once, also when several processes ask
  for it at the same time); returns the builder directory."""
  data_dir = os.fspath(data_dir)
  written = os.path.join(data_dir, builder_class.name, params.name, str(builder_class.VERSION))
  if "://" not in data_dir and os.path.exists(os.path.join(written, "dataset_info.json")):
    return written  # reading needs no builder (nor TensorFlow, which writing does)
  with _one_writer(data_dir, f"{builder_class.name}-{params.name}"):
    builder = builder_class(params=params, data_dir=data_dir, file_format="array_record")
    builder.download_and_prepare()
  return os.fspath(builder.data_dir)
