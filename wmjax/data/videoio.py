"""Reading video files into frames (mp4 through the ffmpeg binary imageio-ffmpeg ships, GIF
through Pillow); the data layer's importers and the evaluation tools share it. imageio-ffmpeg is
imported only for mp4, so GIFs work where it is not installed."""

from __future__ import annotations

import os
import warnings
from typing import Iterator

import numpy as np
from PIL import Image


def ffmpeg():
  """The ``imageio_ffmpeg`` module, or an error that says what needs it and what works without."""
  try:
    import imageio_ffmpeg
  except ImportError as error:
    raise ImportError("mp4 videos need imageio-ffmpeg (pip install imageio-ffmpeg), which is not "
                      "installed here; GIF (.gif) works without it") from error
  return imageio_ffmpeg


def iter_frames(path: str) -> Iterator[np.ndarray]:
  """uint8 frames ``[H, W, 3]`` of an mp4 (or anything ffmpeg reads) or a GIF, decoded one at a
  time; closing the iterator stops the decoder. A missing file is a FileNotFoundError, one ffmpeg
  cannot open a ValueError, each naming it."""
  if path.lower().endswith(".gif"):
    with Image.open(path) as image:
      for index in range(image.n_frames):
        image.seek(index)
        yield np.asarray(image.convert("RGB"))
    return
  if not os.path.isfile(path):
    raise FileNotFoundError(f"no video {path}")
  reader = ffmpeg().read_frames(path)
  try:
    with warnings.catch_warnings():
      warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
      try:
        meta = next(reader)
      except OSError as error:  # ffmpeg's message and its whole log: keep the last line
        lines = [line for line in str(error).splitlines() if line.strip()]
        raise ValueError(f"{path} is not a readable video ({lines[-1] if lines else error})"
                         ) from error
    width, height = meta["size"]
    for frame in reader:
      yield np.frombuffer(frame, np.uint8).reshape(height, width, 3)
  finally:
    reader.close()  # stops the ffmpeg process


def read_video(path: str) -> np.ndarray:
  """uint8 ``[T, H, W, 3]`` from an mp4 (or anything ffmpeg reads) or a GIF."""
  return np.stack(list(iter_frames(path)))


class VideoStream:
  """The frames of one video file read forward in pieces: ``read(start, count)`` returns uint8
  ``[count, H, W, 3]`` from frame ``start`` on, decoding each frame once while the starts
  increase and holding only the frames asked for (a request before the position reopens the
  file). For files holding many episodes (LeRobot v3) one after the other."""

  def __init__(self, path: str):
    self.path = path
    self._frames = None  # iter_frames(path), at frame self._position
    self._position = 0

  def _open(self) -> None:
    self.close()
    self._frames, self._position = iter_frames(self.path), 0

  def read(self, start: int, count: int) -> np.ndarray:
    if self._frames is None or start < self._position:
      self._open()
    frames = []
    for index, frame in enumerate(self._frames, self._position):
      if index >= start:
        frames.append(frame)
      if index + 1 >= start + count:
        break
    if len(frames) != count:
      self.close()
      raise ValueError(f"{self.path}: frames [{start}, {start + count}) asked for, but the "
                       f"video ends before frame {max(start, self._position) + len(frames)}")
    self._position = start + count
    return np.stack(frames)

  def count_rest(self) -> int:
    """How many frames follow the ones read so far (decoding them to the end of the file)."""
    if self._frames is None:
      self._open()
    rest = sum(1 for _ in self._frames)
    self._position += rest
    return rest

  def close(self) -> None:
    if self._frames is not None:
      self._frames.close()
    self._frames = None
