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
