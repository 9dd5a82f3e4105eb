"""An image-based policy with memory: the hand tracked from frame readings and the policy's own
actions.

MetaWorld's Sawyer hand follows a target that each action moves, with a lag: over one frame
(``action_repeat`` control steps) the hand moves by about ``now * a_t + before * a_{t-1}`` per axis
(:class:`HandMotion`, a least-squares fit on a split's recorded episodes; on the default button
data 0.5 cm of error per frame in x and z, 1.6 cm in y where the button stops the hand). A
:class:`TrackedHand` predicts the hand's position from its last estimate and the two actions,
then moves the prediction towards the reader's new reading by ``reading_weight``; the object's
position is the newest reading. ``reading_weight = 1`` is the newest reading alone (no memory).

The same tracker runs in the simulator and in a world model: what changes between the two is only
the frames it reads. It makes a policy as steady against a misread frame as a robot that knows
what it commanded.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class HandMotion:
  """The hand's move over one frame, per axis: ``now [3] * a_t + before [3] * a_{t-1}`` (metres
  per unit action; ``a`` the first three action numbers, clipped to [-1, 1])."""

  now: np.ndarray
  before: np.ndarray

  @classmethod
  def fit(cls, hands, actions) -> "HandMotion":
    """Least squares over episodes: ``hands [N, T, 3]`` (metres) and the ``actions [N, T-1, >=3]``
    between them."""
    hands, actions = np.asarray(hands, np.float64), np.asarray(actions, np.float64)
    if hands.ndim != 3 or actions.ndim != 3 or actions.shape[:2] != (hands.shape[0],
                                                                      hands.shape[1] - 1):
      raise ValueError(f"need hands [N, T, 3] and actions [N, T-1, A], got {hands.shape} and "
                       f"{actions.shape}")
    moves = np.diff(hands[..., :3], axis=1)  # [N, T-1, 3]
    now = np.clip(actions[..., :3], -1.0, 1.0)
    before = np.concatenate([np.zeros_like(now[:, :1]), now[:, :-1]], axis=1)
    coefficients = [np.linalg.lstsq(np.stack([now[..., k].ravel(), before[..., k].ravel()], 1),
                                    moves[..., k].ravel(), rcond=None)[0] for k in range(3)]
    now_c, before_c = np.array(coefficients).T
    return cls(now_c, before_c)

  def move(self, action, previous) -> np.ndarray:
    """``[3]``: the hand's predicted move after ``action`` following ``previous`` (each ``[>=3]``)."""
    clip = lambda a: np.clip(np.asarray(a, np.float64)[:3], -1.0, 1.0)
    return self.now * clip(action) + self.before * clip(previous)

  def to_dict(self) -> dict[str, list[float]]:
    return {"now": self.now.tolist(), "before": self.before.tolist()}


class TrackedHand:
  """One episode's state estimate from readings ``[6]`` (hand then object, metres) and the actions
  taken between them."""

  def __init__(self, motion: HandMotion | None, reading_weight: float = 1.0):
    if not 0.0 < reading_weight <= 1.0:
      raise ValueError(f"reading_weight must be in (0, 1], got {reading_weight}")
    if motion is None and reading_weight < 1.0:
      raise ValueError("tracking the hand (reading_weight < 1) needs a HandMotion")
    self.motion, self.reading_weight = motion, reading_weight
    self._hand = None
    self._actions = [np.zeros(3), np.zeros(3)]  # the last two actions, oldest first

  def update(self, reading) -> np.ndarray:
    """The estimate ``[6]`` after a new frame's ``reading [6]``."""
    reading = np.asarray(reading, np.float64)
    if self._hand is None or self.reading_weight == 1.0:
      self._hand = reading[:3]
    else:
      predicted = self._hand + self.motion.move(self._actions[1], self._actions[0])
      self._hand = predicted + self.reading_weight * (reading[:3] - predicted)
    return np.concatenate([self._hand, reading[3:]]).astype(np.float32)

  def acted(self, action) -> None:
    """Record the action taken after the last frame."""
    self._actions = [self._actions[1], np.asarray(action, np.float64)[:3]]


def fit_hand_motion(builder_dir: str, split: str = "train") -> HandMotion:
  """:meth:`HandMotion.fit` on every episode of a MetaWorld dataset split (the simulator's hand
  positions, ``observation/state``, and the actions between them)."""
  from wmjax.data.sources import ArrayRecordEpisodes
  source = ArrayRecordEpisodes(builder_dir, split)
  episodes = [source.episode(i) for i in range(len(source))]
  return HandMotion.fit(np.stack([e.extras["state"][:, :3] for e in episodes]),
                        np.stack([e.actions[:-1] for e in episodes]))
