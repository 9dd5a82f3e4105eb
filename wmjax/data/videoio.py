"""Reading video files into frames (mp4 through the ffmpeg binary imageio-ffmpeg ships, GIF
through Pillow); the data layer's importers and the evaluation tools share it."""

from __future__ import annotations

import warnings

import imageio_ffmpeg
import numpy as np
from PIL import Image


def read_video(path: str) -> np.ndarray:
  """uint8 ``[T, H, W, 3]`` from an mp4 (or anything ffmpeg reads) or a GIF."""
  if path.lower().endswith(".gif"):
    with Image.open(path) as image:
      frames = []
      for index in range(image.n_frames):
        image.seek(index)
        frames.append(np.asarray(image.convert("RGB")))
    return np.stack(frames)
  reader = imageio_ffmpeg.read_frames(path)
  with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
    meta = next(reader)
  width, height = meta["size"]
  return np.stack([np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader])
