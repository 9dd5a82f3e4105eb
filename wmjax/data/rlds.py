"""RLDS episodes -> training windows, shared by both read paths (tf.data and grain).

An episode's steps arrive *batched* (every feature with a leading step axis ``L``) with images
still encoded, so that only the frames of a window are decoded. A window of ``F`` frames starting
at step ``s`` holds frames ``s .. s+F-1`` and the ``F-1`` actions ``s .. s+F-2`` (action ``j``
moves frame ``j`` to frame ``j+1``: docs/design.md, Tensor conventions).

A window is a dict of numpy arrays:
  frames       uint8 ``[F, H, W, 3]`` fitted to the requested resolution (aspect ratio kept)
  actions      float32 ``[F-1, A]`` assembled by the spec (not yet normalised)
  instruction  bytes (UTF-8)
  episode      int, index of the episode in its split
  start        int, first step of the window
  <extra>      ``[F, ...]`` per-step extras of the spec (last key component as name)
"""

from __future__ import annotations

import dataclasses
import io
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np
from PIL import Image

from wmjax.data.oxe import DatasetSpec, decode_instruction, get_path


@dataclasses.dataclass
class Episode:
  """Steps ``first_step .. first_step+L-1`` of an episode: encoded images ``[L]`` (a tuple of
  encoded views per step for several cameras, or pre-encoded latents ``[L, h, w, c]``),
  assembled actions ``[L, A]``, instruction, per-step extras ``[L, ...]``."""

  images: Sequence[Any]
  actions: np.ndarray
  instruction: str
  extras: dict[str, np.ndarray]
  first_step: int = 0
  index: int = -1  # its place in the split, episodes skipped for a missing camera counted

  def __len__(self) -> int:
    return len(self.images)

  @classmethod
  def from_steps(cls, spec: DatasetSpec, steps: Mapping[str, Any], first_step: int = 0,
                 index: int = -1) -> "Episode":
    """From batched RLDS steps (leading axis L) with the image features left encoded; with
    ``spec.frame_step = k`` the steps are raw steps from ``k * first_step`` on and every k-th
    is kept."""
    k = spec.frame_step
    views = [list(np.asarray(get_path(steps, key), dtype=object).reshape(-1))[::k]
             for key in spec.image_keys]
    instruction = ""
    if spec.instruction_key:
      values = np.asarray(get_path(steps, spec.instruction_key))
      instruction = (decode_instruction(values[0], spec.instruction_encoding) if len(values)
                     else "")
    return cls(
        images=views[0] if len(views) == 1 else list(zip(*views)),
        actions=spec.subsample_actions(spec.actions(steps)),
        instruction=instruction,
        extras={key.split("/")[-1]: np.asarray(get_path(steps, key))[::k]
                for key in spec.extra_keys},
        first_step=first_step, index=index)


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


def no_windows_error(where: str, episodes: int, frames: int) -> ValueError:
  """The error both read paths raise when no episode is long enough for one window."""
  return ValueError(f"{where} has no episode of at least {frames} steps ({episodes} episodes): "
                    f"no window of {frames} frames can be made; lower data.frames or "
                    f"data.frame_step")


def fit_image(image: Image.Image, resolution: tuple[int, int], resize: str) -> Image.Image:
  """Scale ``image`` to ``resolution=(H, W)`` keeping its aspect ratio: ``crop`` takes the
  largest centred region of the target's aspect ratio first, ``pad`` scales it to fit inside and
  centres it on black."""
  height, width = resolution
  w, h = image.size
  if (w, h) == (width, height):
    return image
  if resize == "crop":
    if w * height > h * width:  # too wide: crop the sides
      keep = max(1, round(h * width / height))
      box = ((w - keep) // 2, 0, (w - keep) // 2 + keep, h)
    else:
      keep = max(1, round(w * height / width))
      box = (0, (h - keep) // 2, w, (h - keep) // 2 + keep)
    return image.resize((width, height), Image.BILINEAR, box=box)
  if resize == "pad":
    scale = min(width / w, height / h)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    canvas = Image.new("RGB", (width, height))
    canvas.paste(image.resize(size, Image.BILINEAR),
                 ((width - size[0]) // 2, (height - size[1]) // 2))
    return canvas
  raise ValueError(f"resize must be 'crop' or 'pad', got {resize!r}")


def decode_image(data: bytes | Sequence[bytes], resolution: tuple[int, int] | None,
                 resize: str = "crop") -> np.ndarray:
  """Encoded PNG / JPEG bytes -> uint8 ``[H, W, 3]`` fitted to ``resolution=(H, W)`` (see
  :func:`fit_image`; None: native size). Several views (a tuple) are tiled left to right, each
  fitted to ``(H, W / views)``."""
  if isinstance(data, (tuple, list)):
    if resolution is not None and resolution[1] % len(data):
      raise ValueError(f"a width of {resolution[1]} does not split into {len(data)} views")
    size = None if resolution is None else (resolution[0], resolution[1] // len(data))
    return np.concatenate([decode_image(view, size, resize) for view in data], axis=1)
  image = Image.open(io.BytesIO(data)).convert("RGB")
  if resolution is not None:
    image = fit_image(image, tuple(resolution), resize)
  return np.asarray(image, np.uint8)


def make_window(episode: Episode, start: int, frames: int, resolution: tuple[int, int] | None,
                episode_index: int = -1, resize: str = "crop") -> dict[str, Any]:
  """The window of ``frames`` frames starting at (absolute) step ``start`` (see module doc)."""
  first, stop = start - episode.first_step, start - episode.first_step + frames
  if first < 0 or stop > len(episode):
    raise ValueError(f"window [{start}, {start + frames}) does not fit steps "
                     f"[{episode.first_step}, {episode.first_step + len(episode)})")
  if isinstance(episode.images, np.ndarray):  # pre-encoded latents [L, h, w, c]
    frames = episode.images[first:stop]
  else:
    frames = np.stack([decode_image(episode.images[i], resolution, resize)
                       for i in range(first, stop)])
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
                    episode_index: int = -1, resize: str = "crop") -> Iterator[dict[str, Any]]:
  for start in window_starts(len(episode), frames, stride):
    yield make_window(episode, start, frames, resolution, episode_index, resize)


def stream_windows(episodes: Iterable[Episode], frames: int, stride: int, resolution,
                   resize: str = "crop", where: str = "the dataset") -> Iterator[dict[str, Any]]:
  """Every window of a stream of episodes (the tf.data path), in order; ``episode`` is the
  episode's place in its split (as the ArrayRecord path numbers it), or its place in the stream
  where the episode does not know it. Raises :func:`no_windows_error` when none is long
  enough."""
  count = made = 0
  for position, episode in enumerate(episodes):
    count += 1
    index = episode.index if episode.index >= 0 else position
    for window in episode_windows(episode, frames, stride, resolution, index, resize):
      made += 1
      yield window
  if not made:
    raise no_windows_error(where, count, frames)
