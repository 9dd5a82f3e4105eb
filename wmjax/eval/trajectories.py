"""Held-out trajectories to evaluate on: windows or whole episodes of a split, padded to a common
length with their normalised actions and per-step extras."""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from wmjax.data.pipeline import WindowSource
from wmjax.data.rlds import make_window
from wmjax.data.sources import ArrayRecordEpisodes


@dataclasses.dataclass
class Trajectories:
  """Held-out trajectories padded to a common length ``T``: frames uint8 ``[E, T, H, W, 3]``,
  normalised actions ``[E, T-1, A]``, true lengths ``[E]``, per-step extras ``[E, T, ...]``
  (e.g. ``square_positions``, ``masks``), where each came from (episode, start step), and, for
  pre-encoded data, the model's frames ``[E, T, h, w, c]`` the RGB frames were decoded from."""

  frames: np.ndarray
  actions: np.ndarray
  lengths: np.ndarray
  extras: dict[str, np.ndarray]
  episode: np.ndarray
  start: np.ndarray
  latents: np.ndarray | None = None  # None: the model's frames are the RGB frames encoded

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
                        self.start[index], None if self.latents is None else self.latents[index])


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


def as_masks(masks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
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
