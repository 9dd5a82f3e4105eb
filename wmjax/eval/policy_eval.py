"""Monte Carlo policy evaluation in a world model (WPE section 4, IRASim table 4).

A policy maps the newest frames to an action chunk: ``policy(frames [B, c, H, W, 3] in [-1, 1],
key) -> raw actions [B, k, A]``. Two ways to roll it out closed loop in a world model:

* :func:`env_episodes`: any Python callable, through :class:`wmjax.env.WorldModelEnv` (one jitted
  block per chunk, the policy on the host in between);
* :func:`scan_episodes`: a pure-JAX policy, run inside one jitted ``lax.scan`` over blocks with the
  world model (no host round trip), for large batches of rollouts; a policy that is a pytree of
  arrays (:class:`wmjax.policy.LearnedPolicy`) is an argument of the compiled scan, so a policy
  with new parameters reuses it.

Both sample block ``k`` with ``block_key(rng, k)`` and call the policy with ``fold_in(key, k)``,
so for the same keys they produce the same episodes. A reward function ``(frames [B, T, H, W, 3],
instruction) -> [B]`` (see :mod:`wmjax.eval.rewards`) scores each episode; :func:`policy_value`
gives the mean and standard error of groups of rollouts, and :func:`agreement` compares the values
a world model estimates with ground-truth values: Pearson, Spearman, Kendall, pairwise rank
agreement, whether the ranking is preserved, MMRV and the mean value gap;
:func:`agreement_intervals` gives bootstrap intervals of the correlations over episodes.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike
from scipy import stats as scipy_stats

from wmjax.codecs import Codec, PixelCodec
from wmjax.data.stats import ActionStats
from wmjax.env import RewardFn, WorldModelEnv
from wmjax.eval.metrics import mean_stderr
from wmjax.frames import to_model
from wmjax.model import WorldModel
from wmjax.parallel import mesh_context, replicated_beside, shard_rollout_batch
from wmjax.policy import join_policy, split_policy
from wmjax.rollout import block_key, sample_block_traceable

Policy = Callable[[Any, jax.Array], Any]


def env_episodes(env: WorldModelEnv, policy: Policy, initial_frames, steps: int, key: jax.Array,
                 *, instruction=None, context_actions=None) -> dict[str, np.ndarray]:
  """Roll ``policy`` out for ``steps`` frames in ``env`` from ``initial_frames [B, c0, H, W, 3]``
  (and the raw ``context_actions [B, c0-1, A]`` between them, if known). The policy is called on
  the last ``env.context`` frames whenever its previous chunk is used up (call ``i`` with
  ``fold_in(key, i)``, as :func:`wmjax.tasks.pusht.simulator.simulate_policy` calls it in the
  simulator), and each chunk runs in blocks of at most ``env.horizon`` actions: a policy acts
  the same whatever the model's block length. Returns ``frames [B, c0+steps, H, W, 3]`` in
  [-1, 1] and the raw ``actions [B, steps, A]``."""
  if steps < 1:
    raise ValueError(f"steps must be >= 1, got {steps}")
  env.reset(initial_frames, instruction, context_actions)
  done, actions = 0, []
  for call in itertools.count():
    if done >= steps:
      break
    chunk = np.asarray(policy(env.video()[:, -env.context:], jax.random.fold_in(key, call)))
    _check_chunk(chunk, env.num_envs, env.action_dim)
    chunk = chunk[:, :steps - done]
    for first in range(0, chunk.shape[1], env.horizon):
      env.step(chunk[:, first:first + env.horizon])
    actions.append(chunk)
    done += chunk.shape[1]
  return {"frames": env.video(), "actions": np.concatenate(actions, 1).astype(np.float32)}


def _check_chunk(chunk, batch: int, action_dim: int) -> None:
  if chunk.ndim != 3 or chunk.shape[0] != batch or chunk.shape[2] != action_dim or (
      chunk.shape[1] < 1):
    raise ValueError(f"the policy must return actions [B={batch}, k>=1, A={action_dim}], got "
                     f"shape {tuple(chunk.shape)}")


def scan_episodes(world_model: WorldModel, params: Any, policy: Policy, initial_frames,
                  steps: int, rng: jax.Array, key: jax.Array, *, horizon: int,
                  action_stats: ActionStats | None = None, normalization: str = "mean_std",
                  codec: Codec | None = None, context_actions=None) -> dict[str, jax.Array]:
  """Roll a pure-JAX ``policy`` out for ``steps`` frames inside one jitted scan, as
  :func:`env_episodes` does with an environment of the same ``horizon`` (the same frames for
  the same keys): the window is ``initial_frames [B, c, H, W, 3]`` (``c`` fixed; the model's
  context), the policy gets the window's RGB frames whenever its previous chunk of ``k`` raw
  actions is used up, and each chunk runs in blocks of at most ``horizon`` frames. Returns
  ``frames [B, c+steps, H, W, 3]`` and raw ``actions [B, steps, A]``. The batch is split over
  the local devices when it divides evenly between them."""
  codec = codec or PixelCodec()
  frames = to_model(initial_frames, xp=jnp)
  if frames.ndim != 5:
    raise ValueError(f"initial_frames must be [B, c, H, W, C], got {tuple(frames.shape)}")
  b, c = frames.shape[:2]
  net = world_model.network
  if steps < 1 or horizon < 1 or c + horizon > net.num_frames:
    raise ValueError(f"need steps >= 1 and 1 <= horizon <= {net.num_frames - c} for a "
                     f"{c}-frame window, got steps={steps}, horizon={horizon}")
  a = net.action_dim
  chunk = jax.eval_shape(policy, jax.ShapeDtypeStruct(frames.shape, jnp.float32), key)
  _check_chunk(chunk, b, a)
  known = np.zeros((b, c - 1), bool)
  history = jnp.zeros((b, c - 1, a), jnp.float32)
  if context_actions is not None:
    history = _normalizer(action_stats, normalization, a)(jnp.asarray(context_actions))
    known[:] = True
  window = codec.encode(frames, jax.random.split(rng)[1])
  # The episodes are split over the local devices (when B divides evenly); the scan follows.
  frames, window, history, known = shard_rollout_batch(frames, window, history, jnp.asarray(known))
  static_policy, policy_leaves = split_policy(policy)
  policy_leaves = replicated_beside(policy_leaves, params)
  run = _scan_fn(world_model, static_policy, codec, _StatsKey(action_stats), normalization, steps,
                 -(-steps // chunk.shape[1]), horizon)
  with mesh_context(window):
    frames, actions = run(params, policy_leaves, frames, window, history, known, rng, key)
  return {"frames": frames[:, :c + steps], "actions": actions[:, :steps]}


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
def _scan_fn(world_model, static_policy, codec, stats_key, normalization, steps, num_calls,
             horizon):
  """The jitted closed-loop scan over ``num_calls`` policy calls (``steps`` actions) for one
  (model, policy or policy structure, codec, statistics, shape) combination."""
  normalize = _normalizer(stats_key.stats, normalization, world_model.network.action_dim)

  def block(params, rng, carry, actions, valid, index):
    """One block of ``n <= horizon`` actions ``[B, n, A]`` of which the ``valid [n]`` ones are
    taken: the others and the window's rest up to ``horizon`` are masked and zero, as
    :meth:`WorldModelEnv.step` pads a shorter chunk."""
    rgb, window, history, known = carry
    n = actions.shape[1]
    actions = jnp.where(valid[None, :, None], actions, 0.0)
    padded = jnp.pad(actions, ((0, 0), (0, horizon - n), (0, 0)))
    mask = jnp.pad(valid, (0, horizon - n))
    window_actions = jnp.concatenate([history, padded], 1)
    window_mask = jnp.concatenate([known, jnp.broadcast_to(mask, (known.shape[0], horizon))], 1)
    new = sample_block_traceable(world_model, params, window, window_actions, window_mask,
                                 block_key(rng, index))[:, :n]
    new_rgb = codec.decode(new)
    c = window.shape[1]
    so_far = jnp.concatenate([history, actions], 1)[:, n:]  # the last c-1 stay in the window
    known_so_far = jnp.concatenate([known, jnp.ones(actions.shape[:2], bool)], 1)[:, n:]
    carry = (jnp.concatenate([rgb, new_rgb], 1)[:, -c:], jnp.concatenate([window, new], 1)[:, -c:],
             so_far, known_so_far)
    return carry, new_rgb

  def call(params, policy, rng, key, carry, i):
    raw = policy(carry[0], jax.random.fold_in(key, i))
    actions = normalize(raw)
    k = raw.shape[1]
    blocks = -(-k // horizon)
    valid = i * k + jnp.arange(k) < steps  # the last chunk is cut at the episode's end
    new_rgb = []
    for j in range(blocks):
      part = slice(j * horizon, (j + 1) * horizon)
      carry, rgb = block(params, rng, carry, actions[:, part], valid[part], i * blocks + j)
      new_rgb.append(rgb)
    return carry, (jnp.concatenate(new_rgb, 1), raw)

  @jax.jit
  def run(params, policy_leaves, rgb, window, history, known, rng, key):
    step = functools.partial(call, params, join_policy(static_policy, policy_leaves), rng, key)
    _, (new_rgb, raw) = jax.lax.scan(step, (rgb, window, history, known), jnp.arange(num_calls))
    new_rgb = jnp.moveaxis(new_rgb, 0, 1)  # [B, calls, k, H, W, 3]
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


def agreement(true_values: ArrayLike, estimated_values: ArrayLike) -> dict[str, float]:
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


def agreement_intervals(true_returns, estimated_returns, *, samples: int = 2000, seed: int = 0,
                        level: float = 0.95) -> dict[str, Any]:
  """Bootstrap intervals of :func:`agreement`'s Pearson and Spearman correlations over episodes.

  ``true_returns`` / ``estimated_returns``: per policy (``P >= 3``) the returns of its episodes,
  ``[N_p]`` each, paired (episode ``i`` of a policy started from the same state on both sides).
  Each of ``samples`` draws resamples every policy's episodes with replacement (the same ones on
  both sides), takes the policies' mean returns (NaN returns left out, as in
  :func:`policy_value`) and correlates them. Returns ``pearson`` / ``spearman`` as the
  ``level`` percentile interval ``[lo, hi]`` over the draws where the correlation is defined
  (None if none is), ``undefined_pearson`` / ``undefined_spearman`` (draws where one side's
  means were all equal), ``samples`` and ``level``."""
  if len(true_returns) != len(estimated_returns) or len(true_returns) < 3:
    raise ValueError(f"need returns of the same P >= 3 policies on both sides, got "
                     f"{len(true_returns)} and {len(estimated_returns)}")
  rng = np.random.default_rng(seed)
  means = np.empty((2, samples, len(true_returns)))
  for p, (true, est) in enumerate(zip(true_returns, estimated_returns)):
    true, est = np.asarray(true, np.float64), np.asarray(est, np.float64)
    if true.shape != est.shape or true.ndim != 1 or not len(true):
      raise ValueError(f"policy {p}: need paired [N] returns on both sides, got {true.shape} "
                       f"and {est.shape}")
    draws = rng.integers(0, len(true), (samples, len(true)))
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
      warnings.simplefilter("ignore", RuntimeWarning)  # a draw of only NaN returns
      means[:, :, p] = np.nanmean(true[draws], 1), np.nanmean(est[draws], 1)
  ranks = scipy_stats.rankdata(means, axis=-1)
  result = {"samples": samples, "level": level}
  for name, (x, y) in (("pearson", means), ("spearman", ranks)):
    r = _row_correlation(x, y)
    defined = r[np.isfinite(r)]
    tail = 100 * (1 - level) / 2
    result[name] = ([float(np.percentile(defined, tail)), float(np.percentile(defined, 100 - tail))]
                    if len(defined) else None)
    result[f"undefined_{name}"] = int(samples - len(defined))
  return result


def _row_correlation(x: np.ndarray, y: np.ndarray) -> np.ndarray:
  """Pearson correlation of each row of ``x`` and ``y`` ``[S, P]`` -> ``[S]`` (NaN where a row is
  constant or holds a NaN)."""
  x = x - x.mean(-1, keepdims=True)
  y = y - y.mean(-1, keepdims=True)
  scale = np.sqrt((x * x).sum(-1) * (y * y).sum(-1))
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(scale > 0, (x * y).sum(-1) / scale, np.nan)


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
