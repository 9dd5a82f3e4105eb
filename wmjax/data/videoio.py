"""Reading video files into frames (mp4 through the ffmpeg binary imageio-ffmpeg ships, GIF
through Pillow); the data layer's importers and the evaluation tools share it. imageio-ffmpeg is
imported only for mp4, so GIFs work where it is not installed."""

from __future__ import annotations

import warnings

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


def read_video(path: str) -> np.ndarray:
  """uint8 ``[T, H, W, 3]`` from an mp4 (or anything ffmpeg reads) or a GIF."""
  if path.lower().endswith(".gif"):
    with Image.open(path) as image:
      frames = []
      for index in range(image.n_frames):
        image.seek(index)
        frames.append(np.asarray(image.convert("RGB")))
    return np.stack(frames)
  reader = ffmpeg().read_frames(path)
  with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
    meta = next(reader)
  width, height = meta["size"]
  return np.stack([np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader])


class VideoStream:
  """The frames of one video file read forward in pieces: ``read(start, count)`` returns uint8
  ``[count, H, W, 3]`` from frame ``start`` on, decoding each frame once while the starts
  increase and holding only the frames asked for (a request before the position reopens the
  file). For files holding many episodes (LeRobot v3) one after the other."""

  def __init__(self, path: str):
    self.path = path
    self._generator = None  # imageio-ffmpeg's reader (an ffmpeg process)
    self._frames = None  # frames from self._position on
    self._position = 0

  def _open(self) -> None:
    self.close()
    if self.path.lower().endswith(".gif"):
      self._frames = iter(read_video(self.path))
    else:
      reader = ffmpeg().read_frames(self.path)
      with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        meta = next(reader)
      width, height = meta["size"]
      self._generator = reader
      self._frames = (np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader)
    self._position = 0

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

  def close(self) -> None:
    if self._generator is not None:
      self._generator.close()  # stops the ffmpeg process
    self._generator = self._frames = None
