"""Model-based planning with a world model by ranking (IRASim section 4.3, table 5).

At every replanning step: a proposal samples ``K`` raw action chunks per environment, the world
model imagines all ``B * K`` futures in one batched rollout, a value function scores the imagined
frames, and the best chunk's first ``execute`` actions run in the real environment. ``K = 1`` is
the proposal alone (nothing is imagined).

Proposals (``proposal(frames [B, c, H, W, 3], key, K) -> candidates [B, K, n, A]``):
:func:`policy_proposal` (a stochastic policy sampled ``K`` times, optionally with extra Gaussian
noise) and :func:`sphere_proposal` (IRASim's real-robot planner: straight lines from the current
end-effector position to ``K`` points on a sphere around it).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.codecs import Codec, PixelCodec
from wmjax.data.stats import ActionStats
from wmjax.env import RewardFn
from wmjax.frames import to_model
from wmjax.model import WorldModel
from wmjax.rollout import rollout

Proposal = Callable[[Any, jax.Array, int], Any]


def policy_proposal(policy: Callable[[Any, jax.Array], Any], noise_std: float = 0.0) -> Proposal:
  """``K`` samples of ``policy(frames, key) -> [B, n, A]`` (one call on the frames repeated ``K``
  times), plus Gaussian noise of ``noise_std`` (raw action units)."""
  def propose(frames, key, k):
    frames = jnp.asarray(frames)
    b = frames.shape[0]
    chunks = jnp.asarray(policy(jnp.repeat(frames, k, axis=0), key))
    chunks = chunks.reshape((b, k) + chunks.shape[1:])
    if noise_std:
      chunks = chunks + noise_std * jax.random.normal(jax.random.fold_in(key, 1), chunks.shape)
    return chunks
  return propose


def sphere_proposal(position_fn: Callable[[Any], Any], radius: float, length: int,
                    low: float | None = None, high: float | None = None) -> Proposal:
  """Straight ``length``-step paths from the current position ``position_fn(frame [B, H, W, 3])
  -> [B, A]`` to ``K`` points drawn uniformly on the sphere of ``radius`` around it, clipped to
  ``[low, high]`` when given."""
  def propose(frames, key, k):
    start = jnp.asarray(position_fn(jnp.asarray(frames)[:, -1]), jnp.float32)  # [B, A]
    directions = jax.random.normal(key, (start.shape[0], k, start.shape[1]))
    directions /= jnp.maximum(jnp.linalg.norm(directions, axis=-1, keepdims=True), 1e-8)
    fraction = jnp.arange(1, length + 1, dtype=jnp.float32)[:, None] / length  # [n, 1]
    paths = start[:, None, None] + radius * fraction * directions[:, :, None]
    if low is not None or high is not None:
      paths = jnp.clip(paths, low, high)
    return paths
  return propose


@dataclasses.dataclass(frozen=True)
class Plan:
  """``best [B, n, A]`` raw actions, ``index [B]`` of the chosen candidate, ``scores [B, K]``
  (NaN when ``K = 1``: nothing imagined, unless the planner's ``score_single``), ``candidates
  [B, K, n, A]``, ``imagined [B, K, c+n, H, W, 3]`` (None when nothing was imagined)."""

  best: np.ndarray
  index: np.ndarray
  scores: np.ndarray
  candidates: np.ndarray
  imagined: np.ndarray | None


@dataclasses.dataclass
class Planner:
  """Ranks ``num_candidates`` proposals by ``value(imagined frames [B*K, c+n, H, W, 3],
  instruction) -> [B*K]`` (higher is better) after imagining them with the world model."""

  world_model: WorldModel
  params: Any
  proposal: Proposal
  value: RewardFn
  num_candidates: int
  horizon: int
  action_stats: ActionStats | None = None
  normalization: str = "mean_std"
  codec: Codec = dataclasses.field(default_factory=PixelCodec)
  instruction: Any = None
  score_single: bool = False  # K = 1: imagine and score the one candidate too (else NaN scores)

  def __post_init__(self):
    if self.num_candidates < 1:
      raise ValueError(f"num_candidates must be >= 1, got {self.num_candidates}")

  def _normalize(self, actions):
    if self.action_stats is None:
      return jnp.asarray(actions, jnp.float32)
    return jnp.asarray(self.action_stats.normalize(np.asarray(actions), self.normalization,
                                                   pad_to=self.world_model.network.action_dim))

  def imagine(self, frames, context_actions, candidates, rng: jax.Array) -> np.ndarray:
    """Roll every candidate out from ``frames [B, c, H, W, 3]`` (raw ``context_actions [B, c-1,
    A]`` between them, or None): ``candidates [B, K, n, A]`` -> RGB ``[B, K, c+n, H, W, 3]``."""
    frames = to_model(frames)
    candidates = np.asarray(candidates, np.float32)
    b, k = candidates.shape[:2]
    if candidates.ndim != 4 or b != frames.shape[0]:
      raise ValueError(f"candidates must be [B={frames.shape[0]}, K, n, A], got "
                       f"{candidates.shape}")
    encode_rng, rollout_rng = jax.random.split(rng)
    context = jnp.repeat(self.codec.encode(frames, encode_rng), k, axis=0)
    known = None
    if context_actions is not None:
      known = jnp.repeat(self._normalize(context_actions), k, axis=0)
    actions = self._normalize(candidates.reshape((b * k,) + candidates.shape[2:]))
    latents = rollout(self.world_model, self.params, context, actions, rollout_rng,
                      horizon=self.horizon, context_actions=known)
    imagined = np.asarray(self.codec.decode(latents))
    return imagined.reshape((b, k) + imagined.shape[1:])

  def plan(self, frames, context_actions, key: jax.Array) -> Plan:
    """Propose, imagine, score and pick the best candidate for each environment."""
    proposal_key, rollout_key = jax.random.split(key)
    candidates = np.asarray(self.proposal(to_model(frames), proposal_key,
                                          self.num_candidates), np.float32)
    b, k = candidates.shape[:2]
    if k != self.num_candidates:
      raise ValueError(f"the proposal returned {k} candidates, expected {self.num_candidates}")
    if k == 1 and not self.score_single:
      return Plan(candidates[:, 0], np.zeros(b, int), np.full((b, 1), np.nan), candidates, None)
    imagined = self.imagine(frames, context_actions, candidates, rollout_key)
    flat = imagined.reshape((b * k,) + imagined.shape[2:])
    instruction = self.instruction
    if isinstance(instruction, (list, tuple)):  # one per environment -> one per candidate
      instruction = [text for text in instruction for _ in range(k)]
    scores = np.asarray(self.value(flat, instruction), np.float64).reshape(b, k)
    index = np.argmax(np.where(np.isfinite(scores), scores, -np.inf), axis=1)
    return Plan(candidates[np.arange(b), index], index, scores, candidates, imagined)


def run_closed_loop(planner: Planner, step_fn: Callable[[np.ndarray], np.ndarray],
                    initial_frames, steps: int, key: jax.Array, *, context_actions=None,
                    execute: int | None = None, context: int | None = None
                    ) -> dict[str, Any]:
  """Model-predictive control in a real environment: plan from the newest ``context`` frames,
  run the best chunk's first ``execute`` actions (default: the planner's horizon) through
  ``step_fn(actions [B, A]) -> frames [B, H, W, 3]``, and replan until ``steps`` actions ran.
  ``initial_frames [B, c0, H, W, 3]`` (and raw ``context_actions [B, c0-1, A]``) start the
  episodes. Returns ``frames [B, c0+steps, ...]`` (as ``step_fn`` gives them), ``actions [B,
  steps, A]`` and the list of :class:`Plan` s."""
  frames = [np.asarray(f) for f in np.moveaxis(np.asarray(initial_frames), 1, 0)]
  c0 = len(frames)
  actions = [] if context_actions is None else list(np.moveaxis(np.asarray(context_actions), 1, 0))
  known_from = len(frames) - 1 - len(actions)  # frames before this have no known action
  context = context or c0
  execute = execute or planner.horizon
  plans = []
  while len(frames) - c0 < steps:
    window = np.stack(frames[-context:], 1)
    between = window.shape[1] - 1
    window_actions = None
    if between and len(frames) - context >= known_from:
      window_actions = np.stack(actions[len(actions) - between:], 1)
    plan = planner.plan(window, window_actions, jax.random.fold_in(key, len(plans)))
    plans.append(plan)
    remaining = steps - (len(frames) - c0)
    for action in np.moveaxis(plan.best[:, :min(execute, remaining)], 1, 0):
      frames.append(np.asarray(step_fn(action)))
      actions.append(action)
  start = len(actions) - steps
  return {"frames": np.stack(frames, 1), "actions": np.stack(actions[start:], 1), "plans": plans}
