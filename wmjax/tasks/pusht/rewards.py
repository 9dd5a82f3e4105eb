"""Push-T rewards read from imagined (or rendered) frames."""

from __future__ import annotations

import numpy as np

from wmjax.frames import to_model
from wmjax.tasks.pusht import simulator


def coverage(frames, instruction=None) -> np.ndarray:
  """Push-T coverage of the goal in each rollout's last frame: ``[B, T, H, W, 3]`` (uint8 or in
  [-1, 1]) -> ``[B]``."""
  del instruction
  frames = to_model(frames)
  if frames.ndim != 5 or frames.shape[-1] != 3:
    raise ValueError(f"rollouts must be [B, T, H, W, 3], got shape {tuple(frames.shape)}")
  return np.asarray(simulator.frame_coverage(frames[:, -1]), np.float32)
