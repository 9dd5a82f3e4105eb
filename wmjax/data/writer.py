"""Writing imported episodes as the project's RLDS in ArrayRecord, shared by the importers
(``wmjax data import lerobot | irasim | wpe``).

Every importer writes the same form: a TFDS builder directory whose steps hold
``observation/image`` (PNG) and any other camera ``observation/<name>``, optional float32 vectors
``observation/<name>`` (states), ``action`` float32 ``[A]`` (action ``t`` moves frame ``t`` to frame
``t+1``; the last step's leads nowhere), ``language_instruction`` and ``is_first`` / ``is_last``
/ ``is_terminal``; ``episode_metadata/episode_id`` int64. Episodes keep the order the importer
gives them (shuffling disabled, so ``train[90%:]`` is the last episodes).
"""

from __future__ import annotations

import io
import logging
import os
import shutil
from typing import Any, Callable, Iterable, Mapping

import numpy as np
from PIL import Image

from wmjax.data.videoio import VideoStream, iter_frames
from wmjax.progress import plain

log = logging.getLogger(__name__)

# One split: a callable giving (key, {"steps": [...], "episode_metadata": {...}}) pairs.
SplitExamples = Callable[[], Iterable[tuple[Any, dict]]]


def png(frame: np.ndarray) -> bytes:
  """uint8 ``[H, W, 3]`` -> PNG bytes (lossless: what is read back is the decoded video)."""
  buffer = io.BytesIO()
  Image.fromarray(frame).save(buffer, format="PNG")
  return buffer.getvalue()


def episode_steps(cameras: Mapping[str, np.ndarray], actions: np.ndarray, instruction: str,
                  vectors: Mapping[str, np.ndarray] | None = None) -> list[dict[str, Any]]:
  """The RLDS steps of one episode: ``cameras`` name -> uint8 frames ``[L, H, W, 3]`` (``image``
  is the chosen one), ``actions`` ``[L, A]``, ``vectors`` name -> ``[L, D]`` per-step
  observations (states)."""
  vectors = vectors or {}
  last = len(actions) - 1
  steps = []
  for t in range(len(actions)):
    observation = {name: png(frames[t]) for name, frames in cameras.items()}
    observation.update({name: np.asarray(values[t], np.float32).reshape(-1)
                        for name, values in vectors.items()})
    steps.append({"observation": observation,
                  "action": np.asarray(actions[t], np.float32).reshape(-1),
                  "language_instruction": instruction, "is_first": t == 0,
                  "is_last": t == last, "is_terminal": t == last})
  return steps


def first_frame_shape(video: str) -> tuple[int, int]:
  """``(H, W)`` of a video's first frame (decoding only that one)."""
  frames = iter_frames(video)
  try:
    return next(frames).shape[:2]
  finally:
    frames.close()


def video_steps(video: str, actions: np.ndarray, instruction: str, shape: tuple[int, int],
                vectors: Mapping[str, np.ndarray] | None = None) -> list[dict[str, Any]]:
  """:func:`episode_steps` of a one-camera episode whose frames are ``video``'s first
  ``len(actions)`` and must be of ``shape`` ``(H, W)``; a shorter video, or another size, is an
  error naming the file, a longer one a warning naming it with the frames left out."""
  stream = VideoStream(video)
  try:
    frames = stream.read(0, len(actions))
    left_out = stream.count_rest()
  finally:
    stream.close()
  if frames.shape[1:3] != tuple(shape):
    raise ValueError(f"{video}: frames of {frames.shape[1:3]}, but the dataset's first video has "
                     f"{tuple(shape)}; every video must share one size")
  if left_out:
    log.warning("%s has %d frames but its episode %d actions (one per frame): imported %d steps, "
                "%d frames left out", video, len(actions) + left_out, len(actions), len(actions),
                left_out)
  return episode_steps({"image": frames}, actions, instruction, vectors)


def step_features(image_shapes: Mapping[str, tuple[int, int]], action_dim: int,
                  vector_dims: Mapping[str, int] | None = None) -> dict[str, Any]:
  """The TFDS step features of :func:`episode_steps`' steps: cameras of ``(H, W)`` frames,
  vectors of ``D`` values, ``A``-dim actions."""
  import tensorflow_datasets as tfds
  observation = {name: tfds.features.Image(shape=(int(h), int(w), 3), encoding_format="png")
                 for name, (h, w) in image_shapes.items()}
  observation.update({name: tfds.features.Tensor(shape=(int(dim),), dtype=np.float32)
                      for name, dim in (vector_dims or {}).items()})
  return {"observation": observation,
          "action": tfds.features.Tensor(shape=(int(action_dim),), dtype=np.float32),
          "language_instruction": tfds.features.Text(),
          "is_first": np.bool_, "is_last": np.bool_, "is_terminal": np.bool_}


class NothingDownloaded:
  """Mixin for a TFDS builder that writes data made here: TFDS's lines about downloading and
  "Dataset ... downloaded and prepared" are not printed (nothing is downloaded; the commands say
  what they wrote)."""

  def _log_download_bytes(self) -> None:
    pass

  def _log_download_done(self) -> None:
    pass


def check_out(out: str) -> str:
  """``out`` as a path, or an error when it exists (imports never overwrite)."""
  out = os.fspath(out)
  if os.path.exists(out):
    raise ValueError(f"{out} already exists; refusing to overwrite it")
  return out


def write_builder(out: str, name: str, description: str, step: Mapping[str, Any],
                  splits: Mapping[str, SplitExamples], metadata: Mapping[str, Any]) -> str:
  """Write the builder ``name`` (version 1.0.0) with ``step`` features (:func:`step_features`)
  and ``splits`` into ``out`` (must not exist; written beside it first and renamed when
  complete); ``metadata`` goes into its ``dataset_info.json``. Returns ``out``."""
  import tensorflow_datasets as tfds
  out = check_out(out)

  def _info(self):
    return tfds.core.DatasetInfo(
        builder=self, description=description, disable_shuffling=True,
        features=tfds.features.FeaturesDict({"steps": tfds.features.Dataset(dict(step)),
                                             "episode_metadata": {"episode_id": np.int64}}),
        metadata=tfds.core.MetadataDict(**metadata))

  def _split_generators(self, dl_manager):
    del dl_manager
    return {split: self._generate_examples(examples) for split, examples in splits.items()}

  def _generate_examples(self, examples: SplitExamples):
    yield from examples()

  builder_class = type(f"{name}_import", (NothingDownloaded, tfds.core.GeneratorBasedBuilder), {
      "name": name, "VERSION": tfds.core.Version("1.0.0"), "_info": _info,
      "_split_generators": _split_generators, "_generate_examples": _generate_examples,
  }, skip_registration=True)
  tmp = out.rstrip("/") + ".incomplete"
  shutil.rmtree(tmp, ignore_errors=True)
  try:
    builder = prepare_builder(lambda: builder_class(data_dir=tmp, file_format="array_record"))
    os.rename(builder.data_dir, out)
  finally:
    shutil.rmtree(tmp, ignore_errors=True)
  return out


def prepare_builder(make: Callable[[], Any]) -> Any:
  """Make a TFDS builder with ``make()`` and write its dataset (``download_and_prepare``),
  without TFDS's warning about a config it does not list itself, and, where stderr is no
  terminal, without its progress bars, whose carriage-return updates a log file reads as one
  ever-growing line (they stay off for the rest of the process). Returns the builder."""
  import tensorflow_datasets as tfds
  absl = logging.getLogger("absl")
  level = absl.level
  absl.setLevel(logging.ERROR)
  try:
    builder = make()
  finally:
    absl.setLevel(level)
  if plain():
    tfds.disable_progress_bar()
  builder.download_and_prepare()
  return builder
