"""Video files: side-by-side ground truth | prediction clips as animated GIF."""

from __future__ import annotations

import os

import numpy as np
from PIL import Image

from wmjax.eval.metrics import to_unit


def side_by_side(*videos: np.ndarray, gap: int = 2) -> np.ndarray:
  """Videos ``[T, H, W, 3]`` (same T, H) -> one uint8 video with the panels left to right."""
  panels = [np.round(to_unit(v) * 255).astype(np.uint8) for v in videos]
  t, h = panels[0].shape[:2]
  spacer = np.full((t, h, gap, 3), 255, np.uint8)
  parts = [p for panel in panels for p in (panel, spacer)][:-1]
  return np.concatenate(parts, axis=2)


def write_gif(path: str, video: np.ndarray, fps: float = 4.0, scale: int = 1) -> str:
  """Write uint8 ``[T, H, W, 3]`` as a looping GIF, each pixel scaled ``scale`` times."""
  frames = [Image.fromarray(f).resize((f.shape[1] * scale, f.shape[0] * scale), Image.NEAREST)
            for f in np.asarray(video, np.uint8)]
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
  return path
