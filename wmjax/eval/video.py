"""Video files: ground truth | prediction | difference panels as mp4 (H.264, through the ffmpeg
binary that imageio-ffmpeg ships; imported only for mp4) or GIF (Pillow), and frame grids as PNG.

Videos are ``[T, H, W, 3]``, uint8 or floats in [-1, 1].
"""

from __future__ import annotations

import os
import warnings

import numpy as np
from PIL import Image

from wmjax.data.videoio import ffmpeg
from wmjax.data.videoio import read_video  # noqa: F401 (part of this module's interface)
from wmjax.frames import to_uint8

VIDEO_FORMATS = (".mp4", ".gif")


def difference(pred, target) -> np.ndarray:
  """Absolute per-pixel difference as a uint8 video (black where the frames agree)."""
  return np.abs(to_uint8(pred).astype(np.int16) - to_uint8(target).astype(np.int16)).astype(
      np.uint8)


def side_by_side(*videos, gap: int = 2) -> np.ndarray:
  """Videos ``[T, H, W, 3]`` (same T and H) -> one uint8 video, panels left to right with a
  white ``gap`` between them."""
  panels = [to_uint8(v) for v in videos]
  if len({p.shape[:2] for p in panels}) != 1:
    raise ValueError(f"panels need the same frames and height, got {[p.shape for p in panels]}")
  t, h = panels[0].shape[:2]
  spacer = np.full((t, h, gap, 3), 255, np.uint8)
  parts = [p for panel in panels for p in (panel, spacer)][:-1]
  return np.concatenate(parts, axis=2)


def comparison(truth, pred, gap: int = 2) -> np.ndarray:
  """Ground truth | prediction | difference."""
  return side_by_side(truth, pred, difference(pred, truth), gap=gap)


def stack_rows(videos, gap: int = 2) -> np.ndarray:
  """Videos ``[T, H, W, 3]`` (same T and W) -> one video, rows top to bottom."""
  rows = [to_uint8(v) for v in videos]
  t, _, w = rows[0].shape[:3]
  spacer = np.full((t, gap, w, 3), 255, np.uint8)
  return np.concatenate([p for row in rows for p in (row, spacer)][:-1], axis=1)


def _upscale(video: np.ndarray, scale: int) -> np.ndarray:
  return video.repeat(scale, axis=1).repeat(scale, axis=2) if scale > 1 else video


def default_scale(video) -> int:
  """Nearest-neighbour upscaling that brings small frames to at least ~128 pixels high."""
  return max(1, 128 // np.shape(video)[1])


def write_video(path: str, video, fps: float = 4.0, scale: int | None = None) -> str:
  """Write ``[T, H, W, 3]`` as ``.mp4`` or ``.gif`` (by extension), each pixel repeated
  ``scale`` times (default: :func:`default_scale`). mp4 frames are padded to even sizes."""
  extension = os.path.splitext(path)[1].lower()
  if extension not in VIDEO_FORMATS:
    raise ValueError(f"video path must end in one of {VIDEO_FORMATS}, got {path!r}")
  video = to_uint8(video)
  if video.ndim != 4 or video.shape[-1] != 3 or len(video) == 0:
    raise ValueError(f"a video must be [T, H, W, 3] with T >= 1, got shape {video.shape}")
  video = _upscale(video, default_scale(video) if scale is None else scale)
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  if extension == ".gif":
    frames = [Image.fromarray(f) for f in video]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps),
                   loop=0)
    return path
  pad_h, pad_w = video.shape[1] % 2, video.shape[2] % 2  # yuv420p needs even sizes
  video = np.pad(video, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)))
  writer = ffmpeg().write_frames(path, (video.shape[2], video.shape[1]), fps=fps,
                                 codec="libx264", quality=8, macro_block_size=1,
                                 output_params=["-loglevel", "error"])
  with warnings.catch_warnings():  # JAX warns on any fork; ffmpeg is a fork + exec
    warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
    writer.send(None)
  for frame in video:
    writer.send(np.ascontiguousarray(frame))
  writer.close()
  return path


def frame_grid(videos, gap: int = 2, scale: int | None = None) -> np.ndarray:
  """Videos ``[T, H, W, 3]`` (same shapes) -> one uint8 image ``[H', W', 3]``: a row per video,
  a column per frame, upscaled like :func:`write_video`."""
  rows = [side_by_side(*[frame[None] for frame in to_uint8(v)], gap=gap) for v in videos]
  grid = stack_rows(rows, gap=gap)
  return _upscale(grid, default_scale(videos[0]) if scale is None else scale)[0]


def write_png(path: str, image: np.ndarray) -> str:
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  Image.fromarray(to_uint8(image)).save(path)
  return path
