"""The true gridworld as a gymnasium environment (one episode at a time, for code written against
gymnasium's API; :func:`wmjax.tasks.gridworld.env.run_policy` runs batches inside one jitted
scan). Needs ``gymnasium`` (``pip install "wmjax[gym]"``).

  env = GridworldEnv(ReachTask(GridworldConfig()))
  frame, info = env.reset(seed=0)
  frame, reward, terminated, truncated, info = env.step(env.action_space.sample())
"""

from __future__ import annotations

import gymnasium
import numpy as np

from wmjax.tasks.gridworld import env
from wmjax.tasks.gridworld.dataset import first_centres
from wmjax.tasks.gridworld.reach import ReachTask


class GridworldEnv(gymnasium.Env):
  """The ``reach`` task's gridworld: observations are uint8 frames ``[S, S, 3]``, actions the
  ``2n`` square velocities (pixels/step, in ``[-max_speed, max_speed]``; the red square's are
  ignored, it stays). The reward after step ``t`` is minus the distance of the green square to
  the red one (pixels); an episode terminates on success and is truncated after ``task.steps``
  steps. ``info['centres']`` holds the true square centres ``[n, 2]``; ``reset(options={'centres':
  ...})`` starts from given ones, else from a state drawn as the task draws them."""

  metadata = {"render_modes": ["rgb_array"]}

  def __init__(self, task: ReachTask, render_mode: str | None = "rgb_array"):
    world = task.world
    self.task, self.render_mode = task, render_mode
    self.observation_space = gymnasium.spaces.Box(0, 255, (world.image_size, world.image_size, 3),
                                                  np.uint8)
    self.action_space = gymnasium.spaces.Box(-world.max_speed, world.max_speed,
                                             (2 * world.num_squares,), np.float32)
    self._controls = np.asarray(task.controls)

  def reset(self, *, seed: int | None = None, options: dict | None = None):
    super().reset(seed=seed)
    centres = (options or {}).get("centres")
    if centres is None:
      centres = self._draw_start()
    centres = np.asarray(centres, np.float32)
    shape = (self.task.world.num_squares, 2)
    if centres.shape != shape:
      raise ValueError(f"options['centres'] must be {shape}, got {centres.shape}")
    self._centres, self._first, self._steps = centres, centres, 0
    return self.render(), {"centres": centres}

  def _draw_start(self) -> np.ndarray:
    while True:
      centres = first_centres(self.task.world, self.np_random, 1)[0]
      if self.task.apart(centres):
        return centres

  def step(self, action):
    action = np.asarray(action, np.float32)
    if action.shape != self.action_space.shape:
      raise ValueError(f"action must be {self.action_space.shape}, got {action.shape}")
    self._centres = np.asarray(env.step(self.task.world, self._centres,
                                        np.where(self._controls, action, 0.0)))
    self._steps += 1
    distance = float(np.linalg.norm(self._centres[1] - self._first[0]))
    terminated = distance <= self.task.success_px
    truncated = self._steps >= self.task.steps and not terminated
    return self.render(), -distance, terminated, truncated, {"centres": self._centres}

  def render(self) -> np.ndarray:
    return np.asarray(env.render(self.task.world, self._centres))
