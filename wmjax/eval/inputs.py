"""A user's start frames and action sequences from files, checked against the model
(``wmjax rollout``): every error says what was expected and what came."""

from __future__ import annotations

import csv
import os
from typing import Sequence

import numpy as np
from PIL import Image

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".webp")


def _resize(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  flat = frames.reshape((-1,) + frames.shape[-3:])
  out = [np.asarray(Image.fromarray(f).resize(size[::-1], Image.BILINEAR)) for f in flat]
  return np.stack(out).reshape(frames.shape[:-3] + tuple(size) + (3,))


FLOAT_RANGES = {"-1,1": (-1.0, 1.0), "0,1": (0.0, 1.0)}


def _float_frames_to_uint8(frames: np.ndarray, path: str, value_range: str | None) -> np.ndarray:
  lo, hi = (float(frames.min()), float(frames.max())) if frames.size else (0.0, 0.0)
  if not np.issubdtype(frames.dtype, np.floating) or not np.isfinite(frames).all() or (
      lo < -1.0 or hi > 1.0):
    raise ValueError(f"{path}: frames must be uint8 or finite floats in [-1, 1], got "
                     f"{frames.dtype} in [{lo}, {hi}]")
  if value_range is None:
    if lo >= 0.0:
      raise ValueError(f"{path}: float frames all in [{lo:g}, {hi:g}] are ambiguous ([0, 1] "
                       f"images, or bright frames in [-1, 1]?): say which with --frame_range "
                       f"0,1 or --frame_range -1,1 (value_range=), or give uint8 frames")
    value_range = "-1,1"
  if value_range not in FLOAT_RANGES:
    raise ValueError(f"value_range must be one of {sorted(FLOAT_RANGES)}, got {value_range!r}")
  low, high = FLOAT_RANGES[value_range]
  if lo < low:
    raise ValueError(f"{path}: frames said to be in [{low:g}, {high:g}] go down to {lo:g}")
  return np.round((frames - low) * (255.0 / (high - low))).astype(np.uint8)


def read_frames(paths: Sequence[str], frame_shape: tuple[int, int, int], *,
                resize: bool = False, value_range: str | None = None) -> np.ndarray:
  """Context frames -> uint8 ``[B, c, H, W, 3]``.

  ``paths``: image files (one context frame each, in order, B = 1) or one ``.npy`` holding
  ``[H, W, 3]``, ``[c, H, W, 3]`` or ``[B, c, H, W, 3]`` uint8 frames, or floats in [-1, 1] or,
  with ``value_range='0,1'``, in [0, 1] (floats that are all >= 0 need ``value_range``: they
  could be either). Frames whose size differs from ``frame_shape`` are an error unless
  ``resize``.
  """
  if not paths:
    raise ValueError("no frame files given")
  extensions = {os.path.splitext(p)[1].lower() for p in paths}
  if extensions == {".npy"}:
    if len(paths) != 1:
      raise ValueError(f"give one .npy file of frames, got {len(paths)}")
    frames = np.load(paths[0])
    if frames.dtype != np.uint8:
      frames = _float_frames_to_uint8(frames, paths[0], value_range)
    frames = frames.reshape((1,) * (5 - frames.ndim) + frames.shape) if frames.ndim >= 3 else frames
  elif extensions <= set(IMAGE_EXTENSIONS):
    frames = np.stack([np.asarray(Image.open(p).convert("RGB")) for p in paths])[None]
  else:
    raise ValueError(f"frames must be image files {IMAGE_EXTENSIONS} or one .npy file, got "
                     f"{list(paths)}")
  if frames.ndim != 5 or frames.shape[-1] != 3:
    raise ValueError(f"frames must be RGB [H, W, 3], [c, H, W, 3] or [B, c, H, W, 3], got shape "
                     f"{frames.shape}")
  size = tuple(frame_shape[:2])
  if frames.shape[2:4] != size:
    if not resize:
      raise ValueError(f"frames are {frames.shape[2]}x{frames.shape[3]} but the model was trained "
                       f"on {size[0]}x{size[1]}; resize them or pass --resize")
    frames = _resize(frames, size)
  return frames


def read_actions(path: str, action_dim: int) -> np.ndarray:
  """Raw actions -> float32 ``[B, N, A]`` from ``.npy`` (``[N, A]`` or ``[B, N, A]``) or ``.csv``
  (one action per row, A columns, an optional header row)."""
  extension = os.path.splitext(path)[1].lower()
  if extension == ".npy":
    actions = np.load(path)
  elif extension == ".csv":
    with open(path, newline="") as f:
      rows = [row for row in csv.reader(f) if row]
    try:
      actions = np.array([[float(v) for v in row] for row in rows], np.float64)
    except ValueError:
      try:  # a header row
        actions = np.array([[float(v) for v in row] for row in rows[1:]], np.float64)
      except ValueError as e:
        raise ValueError(f"{path}: every row after the header must hold {action_dim} numbers "
                         f"({e})") from e
  else:
    raise ValueError(f"actions must be a .npy or .csv file, got {path!r}")
  actions = np.asarray(actions)
  if not np.issubdtype(actions.dtype, np.number):
    raise ValueError(f"{path}: actions must be numbers, got dtype {actions.dtype}")
  if actions.ndim == 2:
    actions = actions[None]
  if actions.ndim != 3 or actions.shape[1] == 0:
    raise ValueError(f"{path}: actions must be [N, A] or [B, N, A] with N >= 1, got shape "
                     f"{actions.shape}")
  if actions.shape[-1] != action_dim:
    raise ValueError(f"{path}: the model takes {action_dim}-dim actions, the file has "
                     f"{actions.shape[-1]} per step")
  if not np.isfinite(actions).all():
    raise ValueError(f"{path}: actions contain NaN or inf")
  return actions.astype(np.float32)


def check_action_range(actions: np.ndarray, low: np.ndarray, high: np.ndarray,
                       source: str) -> None:
  """ValueError for raw actions far outside the range the model was trained on (``low`` /
  ``high``, the training data's per-dimension minimum and maximum): more than one training range
  (at least 1) beyond either end, where a model's output means nothing (1e30 gives black frames).
  """
  low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
  margin = np.maximum(high - low, 1.0)
  outside = (actions < low - margin) | (actions > high + margin)
  if outside.any():
    dim = int(np.argwhere(outside)[0][-1])
    values = actions[..., dim]
    raise ValueError(f"{source}: action dimension {dim} takes values in [{values.min():g}, "
                     f"{values.max():g}], but the model was trained on [{low[dim]:g}, "
                     f"{high[dim]:g}]; actions more than {margin[dim]:g} outside that range are "
                     f"refused (pass --allow_extrapolation to roll them out anyway)")
