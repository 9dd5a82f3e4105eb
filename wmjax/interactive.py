"""Driving a world model by hand, as in IRASim's keyboard / VR demos.

:class:`KeyboardDriver` turns key presses into action chunks for a :class:`wmjax.env.WorldModelEnv`
and keeps the episode: each press appends ``chunk`` identical actions and returns the new frames.
Actions are 2-D displacements placed in two slots of the action vector (``axes``); the rest of the
vector is ``rest`` (zeros by default). That fits models whose actions are end-effector
displacements: the gridworld (slots ``(0, 1)`` are square 0's ``(dy, dx)``), Language-Table
(``(dx, dy)``), and the translation part of a 7-D delta pose (``axes=(0, 1)`` with the gripper in
``rest``). ``notebooks/keyboard_control.ipynb`` wires it to the arrow keys.
"""

from __future__ import annotations

import numpy as np

from wmjax.env import WorldModelEnv

# Unit displacement per key in (down, right) image terms.
ARROWS = {"ArrowUp": (-1.0, 0.0), "ArrowDown": (1.0, 0.0), "ArrowLeft": (0.0, -1.0),
          "ArrowRight": (0.0, 1.0)}


class KeyboardDriver:
  """Key presses -> action chunks -> new frames, for a single environment (``B = 1``).

  ``speed``: displacement per step (raw action units); ``axes``: the two action slots that take
  the (vertical, horizontal) displacement, in that order (``(1, 0)`` for (x, y) actions where
  y points down); ``chunk``: actions per key press (default: the env's horizon); ``rest``: the
  other slots' values ``[A]``."""

  def __init__(self, env: WorldModelEnv, *, speed: float = 1.0, axes: tuple[int, int] = (0, 1),
               chunk: int | None = None, rest=None):
    a = env.action_dim
    if len(axes) != 2 or len(set(axes)) != 2 or not all(0 <= i < a for i in axes):
      raise ValueError(f"axes must be two different action slots in [0, {a}), got {axes}")
    self.env, self.speed, self.axes = env, float(speed), tuple(axes)
    self.chunk = chunk or env.horizon
    if not 1 <= self.chunk <= env.horizon:
      raise ValueError(f"chunk must be in [1, {env.horizon}] (the env's horizon), got {chunk}")
    self.rest = np.zeros(a, np.float32) if rest is None else np.asarray(rest, np.float32)
    if self.rest.shape != (a,):
      raise ValueError(f"rest must be [A={a}], got shape {self.rest.shape}")
    self.keys: list[str] = []

  def action(self, key: str) -> np.ndarray:
    """The raw action ``[A]`` a key stands for."""
    if key not in ARROWS:
      raise ValueError(f"key must be one of {sorted(ARROWS)}, got {key!r}")
    action = self.rest.copy()
    for slot, value in zip(self.axes, ARROWS[key]):
      action[slot] = self.speed * value
    return action

  def reset(self, initial_frames, instruction=None) -> np.ndarray:
    """Start from ``initial_frames [1, c0, H, W, 3]``; returns them in [-1, 1]."""
    frames, _ = self.env.reset(initial_frames, instruction)
    if frames.shape[0] != 1:
      raise ValueError(f"the keyboard drives one environment, got B={frames.shape[0]}")
    self.keys = []
    return np.asarray(frames)

  def press(self, key: str) -> np.ndarray:
    """Apply ``chunk`` steps of the key's action; returns the new frames ``[chunk, H, W, 3]``."""
    chunk = np.repeat(self.action(key)[None, None], self.chunk, axis=1)
    frames, *_ = self.env.step(chunk)
    self.keys.append(key)
    return np.asarray(frames[0])

  def video(self) -> np.ndarray:
    """Every frame so far ``[T, H, W, 3]`` in [-1, 1]."""
    return self.env.video()[0]
