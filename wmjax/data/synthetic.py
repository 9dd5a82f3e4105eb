"""A TFDS RLDS builder for datasets wmjax generates itself (gridworld, Push-T), in ArrayRecord.

A subclass names its parameters (a frozen dataclass with ``name``, ``seed``, ``image_size``,
``train_episodes`` and ``test_episodes``), its action dimension, the per-step observation extras,
the episode generator and how to replay a split's start states; this class writes the standard
RLDS layout
(``steps/observation/image`` as PNG, ``steps/action``, ``language_instruction``, ``reward``,
``discount``, ``is_first`` / ``is_last`` / ``is_terminal``) with one builder config per parameter
set, so every variant lives in its own directory and is written once.

Random streams (:func:`stream`): every purpose draws from its own stream of the parameters'
``seed``, so what a model is evaluated or planned on is never what it was trained on by
construction: ``train`` and ``test`` (the dataset's splits) and ``evaluate`` and ``plan`` (start
states a task's evaluation draws; :func:`matching` checks them against the training split's).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import os
from typing import Any, Callable, Iterator

import numpy as np
import tensorflow_datasets as tfds

from wmjax.data.writer import NothingDownloaded, png, prepare_builder
from wmjax.progress import plain


@dataclasses.dataclass
class GeneratedEpisode:
  """``images [L, H, W, 3]`` uint8, ``actions [L, A]`` (step ``t``'s action leads to frame
  ``t + 1``; the last one is never used), ``rewards [L]``, per-step ``observations`` extras, and
  the images of further cameras by feature name (``cameras``, ``{name: [L, H, W, 3]}``, the
  builder's :meth:`SyntheticBuilder.camera_features`)."""

  images: np.ndarray
  actions: np.ndarray
  instruction: str
  rewards: np.ndarray
  observations: dict[str, np.ndarray]
  cameras: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)


# the splits' streams are those the datasets were always written with (``seed + offset``)
_SPLIT_SEED_OFFSETS = {"train": 0, "test": 1_000_003}
SPLITS = tuple(_SPLIT_SEED_OFFSETS)
# other purposes: children of the seed's SeedSequence, apart from the splits' streams and each other
_PURPOSES = ("evaluate", "plan")


def stream(seed: int, purpose: str, *index: int) -> np.random.Generator:
  """The random stream of ``purpose`` (``train``, ``test``, ``evaluate`` or ``plan``) for the
  dataset seed ``seed``; ``index`` picks one of several independent draws of a purpose (e.g. an
  evaluation's own seed). Streams of different purposes never coincide: ``train`` / ``test`` are
  ``default_rng(seed)`` / ``default_rng(seed + 1_000_003)``, the others children
  ``SeedSequence(seed, spawn_key=(k, *index))``."""
  if purpose in _SPLIT_SEED_OFFSETS:
    if index:
      raise ValueError(f"the {purpose!r} split has one stream, got index {index}")
    return np.random.default_rng(seed + _SPLIT_SEED_OFFSETS[purpose])
  if purpose not in _PURPOSES:
    raise ValueError(f"purpose must be one of {SPLITS + _PURPOSES}, got {purpose!r}")
  key = (_PURPOSES.index(purpose), *index)
  return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


def episode_kinds(mix, num_episodes: int) -> np.ndarray:
  """The kind (index into ``mix``: fractions of kinds of episode, e.g. scripted / random / idle
  agents) of each of ``num_episodes`` episodes ``[N]`` int: a weighted round robin, every prefix
  holding each kind's fraction of ``mix`` to within one episode; no randomness (the start states'
  stream is left alone)."""
  mix = np.asarray(mix, np.float64)
  kinds, counts = np.empty(num_episodes, np.int64), np.zeros(len(mix))
  for n in range(num_episodes):
    kinds[n] = int(np.argmax((n + 1) * mix - counts))  # the kind furthest behind its share
    counts[kinds[n]] += 1
  return kinds


def matching(states, reference, atol: float = 1e-6) -> np.ndarray:
  """Whether each of ``states [N, ...]`` equals (every number within ``atol``) one of
  ``reference [M, ...]`` -> ``[N]`` bool."""
  states = np.asarray(states, np.float64)
  reference = np.asarray(reference, np.float64)
  if states.shape[1:] != reference.shape[1:]:
    raise ValueError(f"states {states.shape} and reference {reference.shape} differ in shape")
  found = np.zeros(len(states), bool)
  for first in range(0, len(reference), 1024):  # [N, 1024, ...] at a time
    block = reference[first:first + 1024]
    close = np.abs(states[:, None] - block[None]) <= atol
    found |= close.reshape(close.shape[:2] + (-1,)).all(-1).any(1)
  return found


def unmatched_draws(draw: Callable[[int], np.ndarray], count: int, known, exclude=None
                    ) -> np.ndarray:
  """``count`` states ``[count, ...]`` from calls of ``draw(n)`` (about ``n`` states each, from a
  stream of its own), leaving out every state equal to one of ``known [M, ...]`` (a training
  split's start states) or of ``exclude``: start states held out by construction."""
  known = np.asarray(known)
  if exclude is not None:
    known = np.concatenate([known, np.asarray(exclude, known.dtype)])
  states = []
  while len(states) < count:
    drawn = draw(count)
    states.extend(drawn[~matching(drawn, known)])
  return np.stack(states[:count])


class SyntheticBuilder(NothingDownloaded, tfds.core.GeneratorBasedBuilder):
  """Base builder; subclasses set ``VERSION`` / ``RELEASE_NOTES`` and implement the hooks."""

  def __init__(self, *, params, plain_progress: bool = False, **kwargs):
    self.params, self.plain_progress = params, plain_progress
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

  def camera_features(self) -> tuple[str, ...]:
    """Per-step ``observation/<name>`` images of further cameras besides ``image`` (PNG, square
    at ``image_size`` as ``image``); none by default."""
    return ()

  @classmethod
  def start_states(cls, params, split: str) -> np.ndarray:
    """The start state of every episode of ``split`` (``[N, ...]``, float64), replayed from the
    split's stream without simulating or writing anything."""
    raise NotImplementedError(f"{cls.__name__} must define start_states()")

  @classmethod
  def check_can_write(cls) -> None:
    """Raise, before anything is written, when what the generator needs is missing (a
    simulator's package, say); nothing is needed by default."""

  @staticmethod
  def episode_count(params, split: str) -> int:
    if split not in SPLITS:
      raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return params.train_episodes if split == "train" else params.test_episodes

  # ---------------------------------------------------------------- TFDS
  def _info(self) -> tfds.core.DatasetInfo:
    size = self.params.image_size
    step = {
        "observation": {
            **{name: tfds.features.Image(shape=(size, size, 3), encoding_format="png")
               for name in ("image",) + tuple(self.camera_features())},
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
        metadata=tfds.core.MetadataDict(self.metadata()))

  def metadata(self) -> dict[str, Any]:
    """The parameters written into ``dataset_info.json`` (all of them by default)."""
    return dataclasses.asdict(self.params)

  def _split_generators(self, dl_manager):
    return {split: self._generate_examples(split) for split in SPLITS}

  def _generate_examples(self, split: str):
    rng = stream(self.params.seed, split)
    count = self.episode_count(self.params, split)
    every = max(1, count // 10)  # a plain progress line every tenth of the split (a log file's)
    for index, episode in enumerate(self.episodes(count, rng)):
      if self.plain_progress and ((index + 1) % every == 0 or index + 1 == count):
        print(f"{self.name} {split}: {index + 1}/{count} episodes", flush=True)
      last = len(episode.images) - 1
      steps = [{
          "observation": {"image": png(episode.images[t]),
                          **{k: png(v[t]) for k, v in episode.cameras.items()},
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


def written_dir(builder_class: type[SyntheticBuilder], data_dir: str, params) -> str:
  """Where :func:`prepare` writes (or wrote) the dataset of ``params`` under ``data_dir``."""
  return os.path.join(os.fspath(data_dir), builder_class.name, params.name,
                      str(builder_class.VERSION))


def prepare(builder_class: type[SyntheticBuilder], data_dir: str, params, **options) -> str:
  """Write the dataset as ArrayRecord under ``data_dir`` (once, also when several processes ask
  for it at the same time); returns the builder directory. ``options`` go to the builder (how
  it generates, not what: a Push-T builder's ``workers``)."""
  data_dir = os.fspath(data_dir)
  written = written_dir(builder_class, data_dir, params)
  if "://" not in data_dir and os.path.exists(os.path.join(written, "dataset_info.json")):
    return written  # reading needs no builder (nor TensorFlow, which writing does)
  builder_class.check_can_write()  # before a directory or lock is made
  with _one_writer(data_dir, f"{builder_class.name}-{params.name}"):
    builder = prepare_builder(lambda: builder_class(
        params=params, data_dir=data_dir, file_format="array_record", plain_progress=plain(),
        **options))
  return os.fspath(builder.data_dir)
