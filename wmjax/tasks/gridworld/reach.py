"""A control task in the gridworld whose best action depends on the frame: bring the green square
onto the red one within ``steps`` steps.

The policy moves the green square (square 1, drawn on top); the red one (square 0) stays where it
started (its velocity is 0: the policy does not control it). Everything is read from frames, the
world model's as the simulator's: the red square's centre in the first frame, the green square's
in the last one, and their distance. The return of an episode is minus that distance (pixels);
it succeeds when the distance is at most ``success_px``.

Start states are drawn as the dataset draws an episode's first frame, the two squares at least
``min_separation`` pixels apart along one axis (so that neither hides the other), from the
dataset seed's ``evaluate`` stream for evaluation and its ``plan`` stream for the rollouts a policy
learns from (:func:`wmjax.data.synthetic.stream`): neither is a training split's stream. The
squares sit on a 13 x 13 grid each (the default world), so a draw can still equal a training
episode's first frame by chance: such draws are skipped.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from wmjax.data import synthetic
from wmjax.tasks.gridworld import env
from wmjax.tasks.gridworld.dataset import COLORS, Gridworld, GridworldConfig, first_centres
from wmjax.tasks.gridworld.metrics import color_centroids

TARGET, MOVER = 0, 1  # red stays, green moves


@dataclasses.dataclass(frozen=True)
class ReachTask:
  """``steps`` actions per episode; success within ``success_px`` pixels; start states at least
  ``min_separation`` pixels apart (Chebyshev)."""

  world: GridworldConfig
  steps: int = 8
  success_px: float = 1.0
  min_separation: float = 5.0

  def __post_init__(self):
    if self.world.num_squares < 2:
      raise ValueError(f"the reach task needs 2 squares or more, got {self.world.num_squares}")
    if self.steps < 1:
      raise ValueError(f"steps must be >= 1, got {self.steps}")

  @property
  def controls(self) -> tuple[bool, ...]:
    """The action dimensions a policy sets: the green square's velocity."""
    return tuple(i // 2 == MOVER for i in range(2 * self.world.num_squares))

  demonstration = None  # a policy for the task is cloned from every training episode

  def start_states(self, count: int, purpose: str, index: int = 0, exclude=None) -> np.ndarray:
    """``count`` start states ``[count, n, 2]`` of ``purpose`` (``evaluate`` or ``plan``) and
    draw ``index``, none a training episode's first frame nor one of ``exclude [M, n, 2]``; the
    squares past the second are placed as the data places them."""
    rng = synthetic.stream(self.world.seed, purpose, index)

    def apart(n):
      centres = first_centres(self.world, rng, 4 * n)
      return centres[self.apart(centres)]

    return synthetic.unmatched_draws(apart, count, self._training_starts, exclude)

  def apart(self, centres) -> np.ndarray:
    """Whether the two squares of each of ``centres [..., n, 2]`` are at least
    ``min_separation`` pixels apart along one axis ``[...]``."""
    centres = np.asarray(centres)
    return np.abs(centres[..., MOVER, :] - centres[..., TARGET, :]).max(-1) >= self.min_separation

  @functools.cached_property
  def _training_starts(self) -> np.ndarray:
    """The training split's start states (replayed once per task)."""
    return Gridworld.start_states(self.world, "train")

  @classmethod
  def from_config(cls, config) -> "ReachTask":
    """The task in the gridworld a world model's config (``config.data.gridworld``) trained on."""
    return cls(GridworldConfig.from_saved(config.data.gridworld))

  def describe(self) -> dict:
    return {"name": "reach", "steps": self.steps, "success_px": self.success_px,
            "min_separation": self.min_separation, "gridworld": dataclasses.asdict(self.world)}

  def held_out(self, states) -> bool:
    """Whether none of ``states [N, n, 2]`` is a start state of the gridworld's training split."""
    return not synthetic.matching(states, self._training_starts).any()

  def frames(self, states) -> np.ndarray:
    """The first frames of episodes from ``states [B, n, 2]``: uint8 ``[B, 1, S, S, 3]``."""
    return np.asarray(env.render(self.world, np.asarray(states, np.float32)))[:, None]

  def start(self, states) -> tuple[np.ndarray, None]:
    """How episodes from ``states [B, n, 2]`` begin: their first frames (:meth:`frames`), with no
    action before the policy's."""
    return self.frames(states), None

  def distance(self, frames) -> np.ndarray:
    """Pixels between the red square in the first frame and the green one in the last of
    ``frames [B, T, H, W, 3]`` -> ``[B]``; a square missing from its frame counts the frame's
    size."""
    frames = np.asarray(frames)
    colors = COLORS[:2]
    first, found_first = color_centroids(frames[:, 0], colors)
    last, found_last = color_centroids(frames[:, -1], colors)
    d = np.linalg.norm(last[:, MOVER] - first[:, TARGET], axis=-1)
    return np.where(found_first[:, TARGET] & found_last[:, MOVER], d, frames.shape[-2])

  def reward(self, frames, instruction=None) -> np.ndarray:
    """The episodes' returns ``[B]``: minus :meth:`distance` (a wmjax reward function)."""
    del instruction
    return -self.distance(frames)

  def success(self, frames) -> np.ndarray:
    """Whether each episode ended with the green square on the red one ``[B]``."""
    return self.distance(frames) <= self.success_px

  def run(self, policy, states, key) -> dict:
    """The policy's episodes in the true gridworld from ``states [B, n, 2]``
    (:func:`wmjax.tasks.gridworld.env.run_policy`)."""
    return env.run_policy(self.world, policy, states, self.steps, key)
