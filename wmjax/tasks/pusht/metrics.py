"""Push-T metrics read from frames: where the agent and the T are, and whether the agent is there.

A 3-pixel agent is under 1 % of a 48x48 frame: a prediction that drops it still beats copying
the last frame on MSE, so the pixel metrics cannot tell whether a model simulates Push-T. These
metrics compare the objects a policy reads (:func:`.simulator.object_masks`) in the predicted
and the true frame:

* ``agent_error_px``: distance (frame pixels) between the predicted and the true agent centroid,
  half the frame size where the prediction shows no agent;
* ``agent_found``: whether the prediction shows an agent at all; ``agent_iou``: IoU of the
  agent's predicted and true pixels (a centroid can sit right in the middle of a smear that
  covers every place the agent might be; the IoU cannot);
* ``block_error_px``: the same for the T's centroid; ``block_angle_error_deg``: the difference
  of the T's angles (:func:`block_pose`: its mask's axis of largest spread is the stem's, the
  third moment along it tells the stem's end from the bar's), 180 where the prediction shows no
  T; ``block_iou``: IoU of the T's pixels (position, angle and shape: a T that bends or smears
  loses IoU even where its centroid and angle are right).

:data:`FRAME_METRICS` adds them to ``wmjax evaluate`` and training's evaluation for Push-T.
"""

from __future__ import annotations

import numpy as np

from wmjax.frames import to_model
from wmjax.tasks.pusht.simulator import object_masks
from wmjax.registry import FrameMetrics


def _masks(frames) -> tuple[np.ndarray, np.ndarray]:
  block, agent = object_masks(to_model(np.asarray(frames)))
  return np.asarray(block), np.asarray(agent)


def _centroid(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """``mask [..., H, W]`` -> centroid ``[..., 2]`` (row, column in pixels) and found ``[...]``."""
  h, w = mask.shape[-2:]
  count = mask.sum((-2, -1))
  rows = (mask * (np.arange(h) + 0.5)[:, None]).sum((-2, -1))
  cols = (mask * (np.arange(w) + 0.5)).sum((-2, -1))
  centre = np.stack([rows, cols], -1) / np.maximum(count, 1)[..., None]
  return centre, count > 0


def block_pose(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """The T's pose from its pixels ``mask [..., H, W]``: centroid ``[..., 2]`` (row, column in
  pixels), angle ``[...]`` (radians, the simulator's ``block_angle``: the stem points along
  ``(-sin a, cos a)`` in ``(x, y)``) and found ``[...]``.

  The stem's axis is the mask's axis of largest spread (the T's variance along its stem is 1.7
  times that along its bar), and the stem's end is where the mask reaches farthest from its
  centroid: the third moment along the axis is positive towards it."""
  h, w = mask.shape[-2:]
  m = mask.astype(np.float64)
  n = np.maximum(m.sum((-2, -1)), 1)
  centre, found = _centroid(mask)
  cy, cx = centre[..., 0], centre[..., 1]
  rows, cols = np.arange(h) + 0.5, np.arange(w) + 0.5
  dy = rows[:, None] - cy[..., None, None]  # [..., H, 1]
  dx = cols - cx[..., None, None]  # [..., 1, W]
  sxx, syy, sxy = ((m * d).sum((-2, -1)) / n for d in (dx * dx, dy * dy, dx * dy))
  axis = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # from +x towards +y
  vx, vy = np.cos(axis), np.sin(axis)
  skew = (m * (dx * vx[..., None, None] + dy * vy[..., None, None]) ** 3).sum((-2, -1))
  sign = np.where(skew < 0, -1.0, 1.0)
  angle = np.arctan2(-sign * vx, sign * vy)
  return centre, angle, found


def _angle_difference_deg(a, b) -> np.ndarray:
  """``|a - b|`` of angles in radians, wrapped to [0, 180] degrees."""
  return np.abs(np.degrees(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))))


def pusht_metrics(pred, truth, extras) -> dict[str, np.ndarray]:
  """Per-frame agent and block metrics ``[E, T]`` of ``pred`` against ``truth`` (``[E, T, S, S,
  3]`` uint8, Push-T renders); ``extras`` are not needed."""
  del extras
  pred_block, pred_agent = _masks(pred)
  true_block, true_agent = _masks(truth)
  penalty = pred_block.shape[-1] / 2
  out, found = {}, {}
  for name, p, t in (("agent", pred_agent, true_agent), ("block", pred_block, true_block)):
    p_centre, p_found = _centroid(p)
    t_centre, t_found = _centroid(t)
    error = np.linalg.norm(p_centre - t_centre, axis=-1)
    out[f"{name}_error_px"] = np.where(p_found, error, penalty) * t_found  # nothing to find: 0
    found[name] = p_found | ~t_found
  _, p_angle, p_found = block_pose(pred_block)
  _, t_angle, t_found = block_pose(true_block)
  angle_error = np.where(p_found, _angle_difference_deg(p_angle, t_angle), 180.0)
  out["block_angle_error_deg"] = angle_error * t_found
  out["agent_found"] = found["agent"].astype(np.float64)
  out["agent_iou"] = _iou(pred_agent, true_agent)
  out["block_iou"] = _iou(pred_block, true_block)
  return out


def _iou(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
  """IoU of masks ``[..., H, W]`` -> ``[...]``; 1 where both are empty."""
  union = (pred | truth).sum((-2, -1))
  return np.where(union > 0, (pred & truth).sum((-2, -1)) / np.maximum(union, 1), 1.0)


def pusht_masks(pred, truth, extras) -> np.ndarray:
  """Object masks ``[E, T, S, S]``: the agent's and the T's pixels in the truth or the
  prediction (the masked MSE is taken over them)."""
  del extras
  pred_block, pred_agent = _masks(pred)
  true_block, true_agent = _masks(truth)
  return pred_block | pred_agent | true_block | true_agent


FRAME_METRICS = FrameMetrics(
    compute=pusht_metrics, object_masks=pusht_masks, headline="agent_error_px",
    lower_is_better={"agent_error_px": True, "agent_found": False, "agent_iou": False,
                     "block_error_px": True, "block_angle_error_deg": True,
                     "block_iou": False})
