"""Push-T rewards read from imagined (or rendered) frames.

* :func:`coverage`: the fraction of the goal's pixels that show the block (or the agent on it);
* :func:`rigid_coverage`: the fraction of the goal a rigid T would cover at the pose read from
  the block's pixels, which a T smeared into a blob over the goal cannot inflate.
"""

from __future__ import annotations

import numpy as np

from wmjax.frames import to_model
from wmjax.tasks.pusht import simulator
from wmjax.tasks.pusht.metrics import block_pose

# pixels a side of the grid on which rigid_coverage lays the posed T over the goal
POSE_GRID = 128


def _last_frames(frames) -> np.ndarray:
  """Rollouts ``[B, T, H, W, 3]`` (uint8 or in [-1, 1]) -> their last frames in [-1, 1]."""
  frames = to_model(frames)
  if frames.ndim != 5 or frames.shape[-1] != 3:
    raise ValueError(f"rollouts must be [B, T, H, W, 3], got shape {tuple(frames.shape)}")
  return frames[:, -1]


def coverage(frames, instruction=None) -> np.ndarray:
  """Push-T coverage of the goal in each rollout's last frame: ``[B, T, H, W, 3]`` (uint8 or in
  [-1, 1]) -> ``[B]``."""
  del instruction
  return np.asarray(simulator.frame_coverage(_last_frames(frames)), np.float32)


def rigid_coverage(frames, instruction=None) -> np.ndarray:
  """Push-T coverage of the goal by a rigid T posed as the block in each rollout's last frame:
  ``[B, T, H, W, 3]`` (uint8 or in [-1, 1]) -> ``[B]``; 0 where no block is seen.

  :func:`coverage` counts pixels, so an imagined T that came apart into a blob spread over the
  goal scores more than the T the simulator would show, and a planner that ranks many
  candidates picks such blobs. This reward reads only the block's pose from its pixels (centroid
  and angle, :func:`.metrics.block_pose`) and measures the goal's area the rigid T would cover at
  that pose (on a :data:`POSE_GRID`-pixel grid); on rendered frames it follows the simulator's
  coverage."""
  del instruction
  last = _last_frames(frames)
  block, _ = simulator.object_masks(last)
  centre, angle, found = block_pose(np.asarray(block))
  xy = centre[:, ::-1] * simulator.WORKSPACE / last.shape[-2]  # (row, col) px -> world (x, y)
  body_centre = np.stack([simulator.body_to_world(np.array(simulator.T_CENTROID), (0.0, 0.0, a))
                          for a in angle]).reshape(-1, 2)
  poses = np.concatenate([xy - body_centre, angle[:, None]], -1)
  goal = simulator.goal_mask(POSE_GRID)
  covered = (simulator.t_masks(POSE_GRID, poses) & goal).sum((-2, -1)) / goal.sum()
  return np.where(found, covered, 0.0).astype(np.float32)
