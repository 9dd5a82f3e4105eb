"""Monte Carlo policy evaluation in a world model (WPE section 4, IRASim table 4).

A policy maps the newest frames to an action chunk: ``policy(frames [B, c, H, W, 3] in [-1, 1],
key) -> raw actions [B, k, A]``. Two ways to roll it out closed loop in a world model:

* :func:`env_episodes`: any Python callable, through :class:`wmjax.env.WorldModelEnv` (one jitted
  block per chunk, the policy on the host in between);
* :func:`scan_episodes`: a pure-JAX policy, run inside one jitted ``lax.scan`` over blocks with the
  world model (no host round trip), for large batches of rollouts.

Both sample block ``k`` with ``block_key(rng, k)`` and call the policy with ``fold_in(key, k)``,
so for the same keys they produce the same episodes. A reward function ``(frames [B, T, H, W, 3],
instruction) -> [B]`` (see :mod:`wmjax.eval.rewards`) scores each episode; :func:`policy_value`
gives the mean and standard error of groups of rollouts, and :func:`agreement` compares the values
a world model estimates with ground-truth values: Pearson, Spearman, Kendall, pairwise rank
agreement, whether the ranking is preserved, MMRV and the mean value gap.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats as scipy_stats

from wmjax.codecs import Codec, PixelCodec
from wmjax.data.stats import ActionStats
from wmjax.env import RewardFn, WorldModelEnv
from wmjax.eval.metrics import mean_stderr
from wmjax.frames import to_model
from wmjax.model import WorldModel
from wmjax.parallel import mesh_context, shard_rollout_batch
from wmjax.rollout import block_key, sample_block_traceable

Policy = Callable[[Any, jax.Array], Any]


def env_episodes(env: WorldModelEnv, policy: Policy, initial_frames, steps: int, key: jax.Array,
                 *, instruction=None, context_actions=None) -> dict[str, np.ndarray]:
  """Roll ``policy`` out for ``steps`` frames in ``env`` from ``initial_frames [B, c0, H, W, 3]``
  (and the raw ``context_actions [B, c0-1, A]`` between them, if known). The policy sees the
  last ``env.context`` frames and its chunk is cut to the env's horizon (and to the frames left).
  Returns ``frames [B, c0+steps, H, W, 3]`` in [-1, 1] and the raw ``actions [B, steps, A]``."""
  if steps < 1:
    raise ValueError(f"steps must be >= 1, got {steps}")
  env.reset(initial_frames, instruction, context_actions)
  done, actions = 0, []
  for call in itertools.count():
    if done >= steps:
      break
    chunk = np.asarray(policy(env.video()[:, -env.context:], jax.random.fold_in(key, call)))
    _check_chunk(chunk, env.num_envs, env.action_dim)
    chunk = chunk[:, :min(env.horizon, steps - done)]
    env.step(chunk)
    actions.append(chunk)
    done += chunk.shape[1]
  return {"frames": env.video(), "actions": np.concatenate(actions, 1).astype(np.float32)}


def _check_chunk(chunk, batch: int, action_dim: int) -> None:
  if chunk.ndim != 3 or chunk.shape[0] != batch or chunk.shape[2] != action_dim or (
      chunk.shape[1] < 1):
    raise ValueError(f"the policy must return actions [B={batch}, k>=1, A={action_dim}], got "
                     f"shape {tuple(chunk.shape)}")


def scan_episodes(world_model: WorldModel, params: Any, policy: Policy, initial_frames,
                  num_blocks: int, rng: jax.Array, key: jax.Array, *, horizon: int,
                  action_stats: ActionStats | None = None, normalization: str = "mean_std",
                  codec: Codec | None = None, context_actions=None) -> dict[str, jax.Array]:
  """Roll a pure-JAX ``policy`` out for ``num_blocks`` blocks of ``horizon`` frames inside one
  jitted scan. The window is ``initial_frames [B, c, H, W, 3]`` (``c`` fixed; the model's
  context); the policy gets the window's RGB frames and must return at least ``horizon`` raw
  actions. Returns ``frames [B, c+num_blocks*horizon, H, W, 3]`` and raw ``actions``. The
  batch is split over the local devices when it divides evenly between them."""
  codec = codec or PixelCodec()
  frames = to_model(initial_frames)
  if frames.ndim != 5:
    raise ValueError(f"initial_frames must be [B, c, H, W, C], got {tuple(frames.shape)}")
  b, c = frames.shape[:2]
  net = world_model.network
  if num_blocks < 1 or horizon < 1 or c + horizon > net.num_frames:
    raise ValueError(f"need num_blocks >= 1 and 1 <= horizon <= {net.num_frames - c} for a "
                     f"{c}-frame window, got num_blocks={num_blocks}, horizon={horizon}")
  a = net.action_dim
  known = np.zeros((b, c - 1), bool)
  history = jnp.zeros((b, c - 1, a), jnp.float32)
  if context_actions is not None:
    history = _normalizer(action_stats, normalization, a)(jnp.asarray(context_actions))
    known[:] = True
  window = codec.encode(frames, jax.random.split(rng)[1])
  # The episodes are split over the local devices (when B divides evenly); the scan follows.
  frames, window, history, known = shard_rollout_batch(frames, window, history, jnp.asarray(known))
  run = _scan_fn(world_model, policy, codec, _StatsKey(action_stats), normalization, num_blocks,
                 horizon)
  with mesh_context(window):
    frames, actions = run(params, frames, window, history, known, rng, key)
  return {"frames": frames, "actions": actions}


def _normalizer(action_stats, normalization, action_dim):
  if action_stats is None:
    return lambda actions: jnp.asarray(actions, jnp.float32)
  return lambda actions: action_stats.normalize(actions, normalization, pad_to=action_dim, xp=jnp)


class _StatsKey:
  """Action statistics compared by value, so compiled scans are cached per statistics."""

  def __init__(self, stats: ActionStats | None):
    self.stats = stats
    self._key = None if stats is None else (stats.gripper_dim, *(
        np.asarray(getattr(stats, f)).tobytes() for f in ("mean", "std", "p01", "p99")))

  def __eq__(self, other):
    return isinstance(other, _StatsKey) and self._key == other._key

  def __hash__(self):
    return hash(self._key)


@functools.lru_cache(maxsize=32)
def _scan_fn(world_model, policy, codec, stats_key, normalization, num_blocks, horizon):
  """The jitted closed-loop scan for one (model, policy, codec, statistics, shape) combination."""
  normalize = _normalizer(stats_key.stats, normalization, world_model.network.action_dim)

  def body(params, rng, key, carry, k):
    rgb, window, history, known = carry
    raw = policy(rgb, jax.random.fold_in(key, k))
    if raw.ndim != 3 or raw.shape[0] != rgb.shape[0] or raw.shape[1] < horizon:
      raise ValueError(f"the policy must return actions [B={rgb.shape[0]}, k>={horizon}, A], got "
                       f"shape {tuple(raw.shape)}")
    raw = raw[:, :horizon]
    actions = normalize(raw)
    window_actions = jnp.concatenate([history, actions], 1)
    window_mask = jnp.concatenate([known, jnp.ones(actions.shape[:2], bool)], 1)
    new = sample_block_traceable(world_model, params, window, window_actions, window_mask,
                                 block_key(rng, k))
    new_rgb = codec.decode(new)
    c = window.shape[1]
    keep = window_actions.shape[1] - (c - 1)  # the last c-1 actions stay in the window
    carry = (jnp.concatenate([rgb, new_rgb], 1)[:, -c:], jnp.concatenate([window, new], 1)[:, -c:],
             window_actions[:, keep:], window_mask[:, keep:])
    return carry, (new_rgb, raw)

  @jax.jit
  def run(params, rgb, window, history, known, rng, key):
    step = functools.partial(body, params, rng, key)
    _, (new_rgb, raw) = jax.lax.scan(step, (rgb, window, history, known), jnp.arange(num_blocks))
    new_rgb = jnp.moveaxis(new_rgb, 0, 1)  # [B, K, h, H, W, 3]
    new_rgb = new_rgb.reshape((new_rgb.shape[0], -1) + new_rgb.shape[3:])
    raw = jnp.moveaxis(raw, 0, 1)
    return (jnp.concatenate([rgb, new_rgb], 1),
            raw.reshape(raw.shape[0], -1, raw.shape[-1]).astype(jnp.float32))

  return run


# ----------------------------------------------------------------------------- values


@dataclasses.dataclass(frozen=True)
class PolicyValue:
  """Mean and standard error of a policy's per-rollout returns (``returns [N]``)."""

  mean: float
  stderr: float
  returns: np.ndarray

  def to_dict(self) -> dict:
    return {"mean": self.mean, "stderr": self.stderr, "rollouts": int(len(self.returns))}


def policy_value(returns) -> PolicyValue:
  """Monte Carlo value of one policy from its rollouts' returns ``[N]`` (NaNs — e.g. a judge that
  gave no parseable answer — are left out)."""
  returns = np.asarray(returns, np.float64).reshape(-1)
  kept = returns[np.isfinite(returns)]
  if not len(kept):
    raise ValueError(f"no finite return among {len(returns)} rollouts")
  mean, stderr = mean_stderr(kept)
  return PolicyValue(float(mean), float(stderr), returns)


def episode_returns(frames, reward_fn: RewardFn, instruction=None, *, start: int = 0
                    ) -> np.ndarray:
  """Score each episode ``frames [B, T, H, W, 3]`` (from frame ``start`` on) with ``reward_fn``."""
  frames = np.asarray(frames)
  return np.asarray(reward_fn(frames[:, start:], instruction), np.float64)


def agreement(true_values, estimated_values) -> dict[str, float]:
  """How well estimated policy values ``[P]`` match true ones ``[P]`` (``P >= 3``).

  ``pearson`` / ``spearman`` / ``kendall``: correlations (NaN when either side is constant);
  ``pairwise_rank_agreement``: fraction of policy pairs the estimate orders as the truth does
  (pairs tied in the truth skipped; NaN when all are tied); ``ranking_preserved``: 1.0 when every
  such pair is ordered the same; ``top1``: 1.0 when the best
  policy is the same; ``mmrv``: mean over policies of the largest true-value gap to a policy whose
  order the estimate inverts (SIMPLER's mean maximum rank violation, 0 is best); ``value_gap``:
  mean |estimated - true|."""
  true = np.asarray(true_values, np.float64)
  est = np.asarray(estimated_values, np.float64)
  if true.shape != est.shape or true.ndim != 1 or len(true) < 3:
    raise ValueError(f"need two [P] value vectors with P >= 3, got {true.shape} and {est.shape}")
  if not (np.isfinite(true).all() and np.isfinite(est).all()):
    raise ValueError("policy values must be finite")
  pairs = [(i, j) for i in range(len(true)) for j in range(i + 1, len(true)) if true[i] != true[j]]
  concordant = [np.sign(true[i] - true[j]) == np.sign(est[i] - est[j]) for i, j in pairs]
  inverted = (np.sign(true[:, None] - true[None]) * np.sign(est[:, None] - est[None])) < 0
  violation = np.where(inverted, np.abs(true[:, None] - true[None]), 0.0).max(1)
  pairwise = float(np.mean(concordant)) if concordant else float("nan")
  constant = np.ptp(true) == 0 or np.ptp(est) == 0  # correlations undefined
  return {
      "pearson": np.nan if constant else float(scipy_stats.pearsonr(true, est).statistic),
      "spearman": np.nan if constant else float(scipy_stats.spearmanr(true, est).statistic),
      "kendall": np.nan if constant else float(scipy_stats.kendalltau(true, est).statistic),
      "pairwise_rank_agreement": pairwise,
      "ranking_preserved": float(pairwise == 1.0) if concordant else float("nan"),
      "top1": float(np.argmax(true) == np.argmax(est)),
      "mmrv": float(violation.mean()),
      "value_gap": float(np.abs(est - true).mean()),
  }


def agreement_table(names: list[str], true: list[PolicyValue], estimated: list[PolicyValue],
                    scores: dict[str, float]) -> str:
  """Markdown: one row per policy (true and estimated value ± stderr, rank in each) and the
  agreement scores."""
  true_rank = scipy_stats.rankdata([-v.mean for v in true], method="min")
  est_rank = scipy_stats.rankdata([-v.mean for v in estimated], method="min")
  lines = ["| policy | simulator value | world-model value | simulator rank | world-model rank |",
           "|---|---|---|---|---|"]
  for name, t, e, rt, re in zip(names, true, estimated, true_rank, est_rank):
    lines.append(f"| {name} | {t.mean:.3f} ± {t.stderr:.3f} | {e.mean:.3f} ± {e.stderr:.3f} | "
                 f"{int(rt)} | {int(re)} |")
  lines += ["", "| " + " | ".join(scores) + " |", "|" + "---|" * len(scores),
            "| " + " | ".join(f"{v:.3f}" for v in scores.values()) + " |"]
  return "\n".join(lines)
