"""Push-T as a control task for improving a policy (:mod:`wmjax.train.improve`): push the T onto
its goal within ``steps`` actions, the return read from frames as the goal's coverage in the last
one (:func:`.rewards.coverage`), a success where it reaches ``success_coverage``.

Start states are drawn as the dataset draws an episode's start, from the dataset seed's
``evaluate`` stream for evaluation and its ``plan`` stream for the episodes a policy learns from
(:func:`wmjax.data.synthetic.stream`, as :mod:`.evaluate` draws them); a draw equal to a training
episode's start is skipped. Every episode, in gym-pusht or in a world model, starts from the same
``context`` frames with the agent held still between them (:meth:`.simulator.PushTSimulator.start`).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from wmjax.data import synthetic
from wmjax.frames import to_model
from wmjax.tasks.pusht import rewards, simulator
from wmjax.tasks.pusht.dataset import PushT, PushTConfig

CONTROL_STEPS = 32  # 3.2 s of control at 10 Hz, as the policy evaluation's episodes


@dataclasses.dataclass(frozen=True)
class PushTask:
  """``steps`` policy actions per episode (each held for the data's ``action_repeat`` control
  steps) after ``context`` still frames of ``image_size`` pixels; success at coverage
  ``success_coverage`` or more."""

  world: PushTConfig
  steps: int
  context: int
  image_size: int
  success_coverage: float = 0.5

  def __post_init__(self):
    if self.steps < 1 or self.context < 1:
      raise ValueError(f"steps and context must be >= 1, got {self.steps} and {self.context}")

  @property
  def controls(self) -> None:
    """The action dimensions a policy sets: both (the agent's target position)."""
    return None

  @staticmethod
  def demonstration(episode) -> bool:
    """Whether a policy for the task is cloned from a training ``episode``
    (:class:`wmjax.data.rlds.Episode`): the scripted pushes with action noise, not the
    noiseless ones (their cloned policy would leave little to improve) nor the random and idle
    agents (``policy_noise`` < 0)."""
    return bool(episode.extras["policy_noise"][0] > 0)

  @classmethod
  def from_config(cls, config) -> PushTask:
    """The task in the Push-T world a world model's config trained on: its frame size, rollout
    context and the dataset's action repeat."""
    world = PushTConfig.from_dict(config.data.pusht)
    return cls(world, world.actions_for(CONTROL_STEPS), int(config.rollout.context),
               int(config.frame_shape[0]))

  def describe(self) -> dict:
    return {"name": "push", "steps": self.steps, "context": self.context,
            "image_size": self.image_size, "success_coverage": self.success_coverage,
            "pusht": dataclasses.asdict(self.world)}

  @functools.cached_property
  def _training_starts(self) -> np.ndarray:
    """The training split's start states (replayed once per task)."""
    return PushT.start_states(self.world, "train")

  def start_states(self, count: int, purpose: str, index: int = 0, exclude=None) -> np.ndarray:
    """``count`` simulator states ``[count, 5]`` of ``purpose`` (``evaluate`` or ``plan``) and
    draw ``index``, none a training episode's start nor one of ``exclude [M, 5]``."""
    rng = synthetic.stream(self.world.seed, purpose, index)
    return synthetic.unmatched_draws(
        lambda n: simulator.random_initial_states(rng, n, max_offset=self.world.max_offset,
                                                  max_angle=self.world.max_angle),
        count, self._training_starts, exclude)

  def held_out(self, states) -> bool:
    """Whether none of ``states [N, 5]`` is a start state of the training split."""
    return not synthetic.matching(states, self._training_starts).any()

  def start(self, states) -> tuple[np.ndarray, np.ndarray | None]:
    """How episodes from ``states [B, 5]`` begin, from one simulator run: the ``context`` first
    frames, uint8 ``[B, c, S, S, 3]``, and the still actions between them ``[B, c-1, 2]`` (None
    for one frame)."""
    sim = simulator.PushTSimulator(len(states), self.image_size, self.world.action_repeat)
    frames, actions, _ = sim.start(np.asarray(states), self.context)
    return np.stack(frames, 1), (np.stack(actions, 1).astype(np.float32) if actions else None)

  def reward(self, frames, instruction=None) -> np.ndarray:
    """The episodes' returns ``[B]``: the goal's coverage in the last of ``frames [B, T, H, W,
    3]`` (a wmjax reward function)."""
    return rewards.coverage(frames, instruction)

  def success(self, frames) -> np.ndarray:
    """Whether each episode ended with coverage ``success_coverage`` or more ``[B]``."""
    return self.reward(frames) >= self.success_coverage

  def run(self, policy, states, key) -> dict:
    """The policy's episodes in gym-pusht from ``states [B, 5]``
    (:func:`.simulator.simulate_policy`): frames ``[B, c+steps, S, S, 3]`` in [-1, 1] and the
    policy's raw actions ``[B, steps, 2]`` (the still context actions left out)."""
    out = simulator.simulate_policy(policy, np.asarray(states), self.steps,
                                    image_size=self.image_size, key=key, context=self.context,
                                    action_repeat=self.world.action_repeat)
    return {"frames": to_model(out["frames"]), "actions": out["actions"][:, self.context - 1:]}
