"""A rollout from the user's own start frames and raw actions (``wmjax rollout``): the actions
checked against the training range and normalised with the checkpoint's statistics, the horizon
fitted to the model's window, the frames generated and written as videos, a grid and ``.npy``."""

from __future__ import annotations

import os

import jax
import numpy as np

from wmjax.eval import inputs
from wmjax.eval import video as video_lib
from wmjax.frames import to_model, to_uint8
from wmjax.rollout import rollout


def rollout_horizon(model, context: int, horizon: int | None) -> int:
  """Frames per block: ``horizon`` if it fits the model's window after ``context`` frames (else
  ValueError), by default the config's rollout horizon fitted to the window."""
  window = model.config.model.num_frames
  room = window - context
  if room < 1:
    raise ValueError(f"{context} context frames leave no room in the model's {window}-frame "
                     f"window")
  if horizon is not None and not 1 <= horizon <= room:
    raise ValueError(f"--horizon must be between 1 and {room} (the model's {window}-frame window "
                     f"less {context} context frame(s)), got {horizon}")
  return horizon or min(model.config.rollout.horizon, room)


def model_actions(model, actions: np.ndarray, normalized: bool = False,
                  allow_extrapolation: bool = False, source: str = "actions") -> np.ndarray:
  """Raw actions [B, N, A] (or already ``normalized`` ones) -> the model's normalised, padded
  actions; ValueError for values far outside the training range unless ``allow_extrapolation``."""
  stats, mode = model.action_stats, model.config.data.normalization
  if not allow_extrapolation:
    low, high = stats.min, stats.max
    if normalized:
      low, high = stats.normalize(low[None], mode)[0], stats.normalize(high[None], mode)[0]
    inputs.check_action_range(actions, low, high, source)
  return stats.normalize(actions, "none" if normalized else mode,
                         pad_to=model.config.model.action_dim)


def roll_out(model, frames: np.ndarray, actions: np.ndarray, horizon: int,
             seed: int = 0) -> np.ndarray:
  """uint8 start frames [B, c, H, W, 3] and model actions [B, N, A] -> uint8 frames
  [B, c + N, H, W, 3] (context included); ValueError on NaN / inf output."""
  if len(frames) != len(actions):
    raise ValueError(f"{len(frames)} start-frame sets but {len(actions)} action sequences")
  encode_key, rollout_key = jax.random.split(jax.random.key(seed))
  context = model.codec.encode(to_model(frames), encode_key)
  latents = rollout(model.world_model, model.params, context, actions, rollout_key,
                    horizon=horizon)
  decoded = np.asarray(model.codec.decode(latents))
  if not np.isfinite(decoded).all():
    raise ValueError("the model produced NaN / inf frames from these inputs; nothing was written")
  return to_uint8(decoded)


def write_rollout(out: str, frames: np.ndarray, fps: float) -> None:
  """``out``/frames.npy, rollout.mp4 and rollout.gif (one row per rollout) and grid.png."""
  os.makedirs(out, exist_ok=True)
  np.save(os.path.join(out, "frames.npy"), frames)
  video = video_lib.stack_rows(list(frames))
  for name in ("rollout.mp4", "rollout.gif"):
    video_lib.write_video(os.path.join(out, name), video, fps=fps)
  video_lib.write_png(os.path.join(out, "grid.png"), video_lib.frame_grid(list(frames)))
