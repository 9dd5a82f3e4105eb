"""RLDS episodes -> training windows, shared by both read paths (tf.data and grain).

An episode's steps arrive *batched* (every feature with a leading step axis ``L``) with images
still encoded, so that only the frames of a window are decoded. A window of ``F`` frames starting
at step ``s`` holds frames ``s .. s+F-1`` and the ``F-1`` actions ``s .. s+F-2`` (action ``j``
moves frame ``j`` to frame ``j+1``, DESIGN.md alignment).

A window is a dict of numpy arrays:
  frames       uint8 ``[F, H, W, 3]`` at the requested resolution
  actions      float32 ``[F-1, A]`` standardised (not yet normalised)
  instruction  bytes (UTF-8)
  episode      int, index of the episode in its split
  start        int, first step of the window
  <extra>      ``[F, ...]`` per-step extras of the spec (last key component as name)
"""

from __future__ import annotations

import dataclasses
import io
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
from PIL import Image

from wmjax.data.oxe import DatasetSpec, decode_instruction, get_path


@dataclasses.dataclass
class Episode:
  """Steps ``first_step .. first_step+L-1`` of an episode: encoded images ``[L]`` (or
  pre-encoded latents ``[L, h, w, c]``), standardised actions ``[L, A]``, instruction, per-step
  extras ``[L, ...]``."""

  images: Sequence[bytes]
  actions: np.ndarray
  instruction: str
  extras: dict[str, np.ndarray]
  first_step: int = 0

  def __len__(self) -> int:
    return len(self.images)

  @classmethod
  def from_steps(cls, spec: DatasetSpec, steps: Mapping[str, Any], first_step: int = 0
                 ) -> "Episode":
    """From batched RLDS steps (leading axis L) with the image feature left encoded."""
    instructions = np.asarray(get_path(steps, spec.instruction_key))
    return cls(
        images=list(np.asarray(get_path(steps, spec.image_key), dtype=object).reshape(-1)),
        actions=spec.actions(steps),
        instruction=decode_instruction(instructions[0]) if len(instructions) else "",
        extras={key.split("/")[-1]: np.asarray(get_path(steps, key)) for key in spec.extra_keys},
        first_step=first_step)


def stack_steps(steps: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
  """Per-step nested dicts -> one nested dict of arrays with a leading step axis."""
  first = steps[0]
  if isinstance(first, Mapping):
    return {k: stack_steps([s[k] for s in steps]) for k in first}
  if isinstance(first, (bytes, str)):
    return np.array(list(steps), dtype=object)
  return np.stack([np.asarray(s) for s in steps])


def window_starts(length: int, frames: int, stride: int) -> range:
  """First steps of the windows of an episode of ``length`` steps (empty when it is too short)."""
  if frames < 2 or stride < 1:
    raise ValueError(f"windows need frames >= 2 and stride >= 1, got frames={frames}, "
                     f"stride={stride}")
  return range(0, max(length - frames + 1, 0), stride)


def decode_image(data: bytes, resolution: tuple[int, int] | None) -> np.ndarray:
  """Encoded PNG / JPEG bytes -> uint8 ``[H, W, 3]``, resized (bilinear) to ``resolution=(H, W)``."""
  image = Image.open(io.BytesIO(data)).convert("RGB")
  if resolution is not None and image.size != (resolution[1], resolution[0]):
    image = image.resize((resolution[1], resolution[0]), Image.BILINEAR)
  return np.asarray(image, np.uint8)


def make_window(episode: Episode, start: int, frames: int, resolution: tuple[int, int] | None,
                episode_index: int = -1) -> dict[str, Any]:
  """The window of ``frames`` frames starting at (absolute) step ``start`` (see module doc)."""
  first, stop = start - episode.first_step, start - episode.first_step + frames
  if first < 0 or stop > len(episode):
    raise ValueError(f"window [{start}, {start + frames}) does not fit steps "
                     f"[{episode.first_step}, {episode.first_step + len(episode)})")
  if isinstance(episode.images, np.ndarray):  # pre-encoded latents [L, h, w, c]
    frames = episode.images[first:stop]
  else:
    frames = np.stack([decode_image(episode.images[i], resolution) for i in range(first, stop)])
  window = {
      "frames": frames,
      "actions": episode.actions[first:stop - 1].astype(np.float32),
      "instruction": episode.instruction.encode("utf-8"),
      "episode": np.int64(episode_index),
      "start": np.int64(start),
  }
  for name, values in episode.extras.items():
    window[name] = values[first:stop]
  return window


def episode_windows(episode: Episode, frames: int, stride: int, resolution,
                    episode_index: int = -1) -> Iterator[dict[str, Any]]:
  for start in window_starts(len(episode), frames, stride):
    yield make_window(episode, start, frames, resolution, episode_index)


def skip_image_decoding(spec: DatasetSpec):
  """TFDS ``decoders`` that leave the spec's image feature encoded (nested like the features)."""
  import tensorflow_datasets as tfds
  decoders: dict[str, Any] = tfds.decode.SkipDecoding()
  for key in reversed(("steps/" + spec.image_key).split("/")):
    decoders = {key: decoders}
  return decoders
