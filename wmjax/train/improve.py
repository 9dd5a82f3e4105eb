"""Improving a policy from its own imagined episodes, and checking the improvement where it
matters.

One round (:func:`collect`, then :func:`wmjax.train.policy.fit_policy`): roll the policy out
with exploration noise from many start states in a model of the environment (a world model,
through :func:`wmjax.eval.policy_eval.scan_episodes`, in one jitted scan; or, as an upper bound,
the true environment), score every episode from its frames, weight the episodes (filtered behaviour
cloning keeps the best ``keep`` fraction; reward-weighted regression weighs each by
``exp((return - best) / beta)``), and fit the policy to the decisions of the weighted episodes.

:func:`improve` runs rounds and, before the first and after each, asks ``check`` for the
policy's values; :func:`task_check` is the check a task with a true environment offers: the
deterministic policy's returns from held-out start states in the true environment and in the
world model, each paired with the starting policy's (gain and its standard error) and the gap
between imagined and true value (how much of the improvement exploits the model's errors).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import jax
import numpy as np

from wmjax.eval.metrics import mean_stderr
from wmjax.eval.policy_eval import scan_episodes
from wmjax.model import LoadedModel
from wmjax.policy import LearnedPolicy
from wmjax.train.policy import decision_batches, fit_policy

# (policy, key) -> {"frames": [B, c+T, H, W, 3] in [-1, 1], "actions": raw [B, T, A]}
Rollout = Callable[[LearnedPolicy, jax.Array], dict]
# frames [B, T, H, W, 3] -> returns [B]
Score = Callable[[np.ndarray], np.ndarray]
WEIGHTINGS = ("filter", "rwr")
log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class ImproveSettings:
  """``rounds`` of ``rollouts`` episodes with noise ``temperature`` (x the policy's own standard
  deviation); ``weighting`` ``filter`` keeps the best ``keep`` fraction, ``rwr`` weighs by
  ``exp((return - best) / beta)``; each round fits ``fit_steps`` Adam steps of ``batch_size``
  decisions at ``learning_rate``, on this round's kept decisions or, with ``replay``, on those of
  every round so far. With ``group`` > 1 the episodes start from ``rollouts / group`` states,
  ``group`` episodes each, and every episode is weighed against its own state's (``filter`` keeps
  the best ``keep`` fraction of each group, ``rwr``'s best is the group's): where the return
  depends on the start as much as on the actions, an easy start then does not pass for a good
  action."""

  rounds: int = 3
  rollouts: int = 1024
  group: int = 1
  temperature: float = 1.0
  weighting: str = "filter"
  keep: float = 0.1
  beta: float = 1.0
  fit_steps: int = 150
  batch_size: int = 64
  learning_rate: float = 1e-3
  replay: bool = False
  seed: int = 0

  def __post_init__(self):
    if self.weighting not in WEIGHTINGS:
      raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
    if not 0 < self.keep <= 1:
      raise ValueError(f"keep must be in (0, 1], got {self.keep}")
    if self.group < 1 or self.rollouts % self.group:
      raise ValueError(f"group must be >= 1 and divide rollouts ({self.rollouts}), got "
                       f"{self.group}")
    if self.rounds < 1 or self.rollouts < 1 or self.fit_steps < 1 or self.beta <= 0:
      raise ValueError("rounds, rollouts and fit_steps must be >= 1 and beta > 0, got "
                       f"{self.rounds}, {self.rollouts}, {self.fit_steps}, {self.beta}")


def episode_weights(returns: np.ndarray, settings: ImproveSettings) -> np.ndarray:
  """Per-episode weights ``[B]`` from the returns ``[B]`` (non-finite returns weigh 0): with
  ``settings.group`` > 1 each consecutive ``group`` episodes (one start state's) among
  themselves, else all of them together."""
  returns = np.asarray(returns, np.float64)
  if len(returns) % settings.group:
    raise ValueError(f"{len(returns)} returns do not split into groups of {settings.group}")
  if not np.isfinite(returns).any():
    raise ValueError("no episode has a finite return")
  pools = returns.reshape(-1, settings.group) if settings.group > 1 else returns[None]
  return np.concatenate([_pool_weights(pool, settings) for pool in pools])


def _pool_weights(returns: np.ndarray, settings: ImproveSettings) -> np.ndarray:
  """Weights ``[P]`` of returns ``[P]`` weighed among themselves (zeros where none is finite)."""
  finite = np.isfinite(returns)
  if not finite.any():
    return np.zeros(len(returns))
  if settings.weighting == "rwr":
    return np.where(finite, np.exp((returns - returns[finite].max()) / settings.beta), 0.0)
  count = max(1, int(round(settings.keep * finite.sum())))
  best = np.argsort(np.where(finite, -returns, np.inf), kind="stable")[:count]
  weights = np.zeros(len(returns))
  weights[best] = 1.0
  return weights


def decisions(episodes: dict, policy: LearnedPolicy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """The policy's decisions in ``episodes`` (``frames [B, c+T, ...]``, raw ``actions [B, T, A]``):
  what it saw ``[B*D, c, H, W, 3]``, its normalised chunks ``[B*D, k, A]`` and their episode
  ``[B*D]``, for the ``D = T // k`` whole chunks."""
  frames, actions = np.asarray(episodes["frames"]), np.asarray(episodes["actions"])
  c, k = policy.context, policy.chunk
  b, t = actions.shape[:2]
  count = t // k
  if count < 1:
    raise ValueError(f"episodes of {t} actions hold no whole chunk of {k}")
  seen = np.stack([frames[:, i * k:i * k + c] for i in range(count)], 1)
  chunks = actions[:, :count * k].reshape(b, count, k, -1)
  normalised = np.asarray(policy.normalize(chunks))
  return (seen.reshape((-1,) + seen.shape[2:]), normalised.reshape((-1, k, actions.shape[-1])),
          np.repeat(np.arange(b), count))


def collect(policy: LearnedPolicy, rollout: Rollout, score: Score, settings: ImproveSettings,
            key: jax.Array) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], dict]:
  """The weighted decisions of one round's noisy episodes: (frames ``[N, c, H, W, 3]``,
  normalised actions ``[N, k, A]``, weights ``[N]``), and what happened (``explore_return``
  mean ± s.e., episodes kept and their mean return)."""
  episodes = rollout(policy.with_temperature(settings.temperature), key)
  returns = np.asarray(score(np.asarray(episodes["frames"])), np.float64)
  weights = episode_weights(returns, settings)
  frames, actions, episode = decisions(episodes, policy)
  mean, stderr = mean_stderr(returns[np.isfinite(returns)])
  record = {"explore_return": float(mean), "explore_return_stderr": float(stderr),
            "kept_episodes": int((weights > 0).sum()),
            "kept_return": float(np.average(np.nan_to_num(returns), weights=weights))}
  per_decision = weights[episode].astype(np.float32)
  kept = per_decision > 0
  return (frames[kept], actions[kept], per_decision[kept]), record


def improve(policy: LearnedPolicy, rollout: Rollout, score: Score, settings: ImproveSettings,
            check: Callable[[LearnedPolicy], dict] | None = None
            ) -> tuple[LearnedPolicy, list[dict]]:
  """``settings.rounds`` rounds: :func:`collect`, then fit the policy to the decisions kept this
  round (with ``settings.replay``, every round so far). With ``settings.group`` > 1, ``rollout``
  must start each consecutive ``group`` episodes from one state (:func:`improve_on_task`'s do).
  Returns the final policy and one record per round (round 0: the starting policy), each with
  ``check(policy)`` when given."""
  key = jax.random.key(settings.seed)
  history = [{"round": 0, **(check(policy) if check else {})}]
  _log_round(history[-1])
  memory = []
  for r in range(1, settings.rounds + 1):
    kept, record = collect(policy, rollout, score, settings, jax.random.fold_in(key, r))
    memory = memory + [kept] if settings.replay else [kept]
    frames, actions, weights = (np.concatenate(parts) for parts in zip(*memory))
    batches = decision_batches(frames, actions, weights, settings.batch_size,
                               seed=settings.seed * 1000 + r)
    policy, losses = fit_policy(policy, batches, settings.fit_steps, settings.learning_rate)
    history.append({"round": r, **record, "decisions": int(len(frames)),
                    "fit_loss": float(losses[-10:].mean()), **(check(policy) if check else {})})
    _log_round(history[-1])
  return policy, history


def _log_round(record: dict) -> None:
  """One line of a round's record (round 0: the starting policy), without per-episode values."""
  log.info("round %d: %s", record["round"],
           {k: v for k, v in record.items() if k not in ("round", "true_returns")})


# ----------------------------------------------------------------------------- a task's rollouts


def world_model_rollout(model: LoadedModel, task, states: np.ndarray) -> Rollout:
  """Episodes of ``task.steps`` actions in the world model from ``states`` (the task renders
  how they begin: ``task.start(states) -> (uint8 frames [B, c, H, W, 3], the raw actions between
  them [B, c-1, A] or None)``), one jitted scan per call."""
  frames, context_actions = task.start(states)

  def rollout(policy: LearnedPolicy, key: jax.Array) -> dict:
    return scan_episodes(model.world_model, model.params, policy, frames, task.steps,
                         jax.random.fold_in(key, 1), key, horizon=model.config.rollout.horizon,
                         action_stats=model.action_stats,
                         normalization=model.config.data.normalization, codec=model.codec,
                         context_actions=context_actions)

  return rollout


def true_rollout(task, states: np.ndarray) -> Rollout:
  """Episodes of ``task.steps`` actions in the task's true environment from ``states``."""
  return lambda policy, key: task.run(policy, states, key)


def paired_gain(returns: np.ndarray, baseline: np.ndarray) -> tuple[float, float]:
  """Mean and standard error of ``returns - baseline`` over the same start states ``[N]``."""
  return tuple(float(v) for v in mean_stderr(np.asarray(returns) - np.asarray(baseline)))


def task_check(task, states: np.ndarray, imagine: Rollout | None, key: jax.Array
               ) -> Callable[[LearnedPolicy], dict]:
  """The values a round records: the deterministic policy from held-out ``states`` ``[N, ...]``
  in the true environment (``true_value`` ± s.e., ``true_success``) and, with ``imagine``, in the
  world model (``imagined_value``, ``gap`` = imagined - true); from the second call on also the
  paired gain over the first call's policy (``true_gain`` ± ``true_gain_stderr``) and the
  per-state returns (``true_returns``)."""
  first: dict = {}

  def check(policy: LearnedPolicy) -> dict:
    deterministic = policy.with_temperature(0.0)
    frames = np.asarray(true_rollout(task, states)(deterministic, key)["frames"])
    true = task.reward(frames)
    mean, stderr = mean_stderr(true)
    out = {"true_value": float(mean), "true_value_stderr": float(stderr),
           "true_success": float(task.success(frames).mean())}
    first.setdefault("true", true)
    out["true_gain"], out["true_gain_stderr"] = paired_gain(true, first["true"])
    if imagine is not None:
      imagined = np.asarray(imagine(deterministic, key)["frames"])
      out["imagined_value"] = float(task.reward(imagined).mean())
      out["imagined_success"] = float(task.success(imagined).mean())
      out["gap"] = out["imagined_value"] - out["true_value"]
    out["true_returns"] = [float(v) for v in true]
    return out

  return check


def improve_on_task(model: LoadedModel, policy: LearnedPolicy, task, settings: ImproveSettings,
                    *, evaluation_states: int = 128, evaluation_draw: int = 0,
                    in_true_environment: bool = False, imagine: bool = True
                    ) -> tuple[LearnedPolicy, dict]:
  """Improve ``policy`` on ``task`` in ``model`` (or, ``in_true_environment``, in the task's true
  environment: the upper bound) from the task's ``plan`` start states, checked after every round
  on ``evaluation_states`` held-out start states of the ``evaluate`` stream's draw
  ``evaluation_draw`` (none of which is a training
  episode's start or a state the policy learns from). Returns the final policy and a report: the
  settings, ``held_out`` (checked: the evaluation states are no training start state), and one
  record per round (:func:`task_check`). ``imagine=False`` leaves the world model out of the
  checks (no ``imagined_value`` or ``gap``): with ``in_true_environment`` the world model's
  network then never runs, only its config, action statistics and frame shape are read."""
  if policy.context != model.config.rollout.context:
    raise ValueError(f"the policy reads {policy.context} frames, the world model's rollouts keep "
                     f"{model.config.rollout.context} (rollout.context)")
  evaluation = task.start_states(evaluation_states, "evaluate", evaluation_draw)
  imagination = np.repeat(task.start_states(settings.rollouts // settings.group, "plan",
                                            exclude=evaluation), settings.group, axis=0)
  rollout = (true_rollout(task, imagination) if in_true_environment
             else world_model_rollout(model, task, imagination))
  check = task_check(task, evaluation,
                     world_model_rollout(model, task, evaluation) if imagine else None,
                     jax.random.key(settings.seed + 1))
  policy, history = improve(policy, rollout, task.reward, settings, check)
  report = {"improved_in": "true environment" if in_true_environment else "world model",
            "settings": dataclasses.asdict(settings), "task": task.describe(),
            "world_model_step": model.step, "evaluation_states": evaluation_states,
            "evaluation_draw": evaluation_draw,
            "held_out": task.held_out(evaluation), "rounds": history}
  return policy, report


def report_table(report: dict) -> str:
  """Markdown: one row per round of :func:`improve_on_task`'s report."""
  lines = [f"Improved in the {report['improved_in']}; checked from {report['evaluation_states']} "
           f"held-out start states (held out: {report['held_out']}).", "",
           "| round | true value | true gain (paired) | true success | imagined value | gap |",
           "|---|---|---|---|---|---|"]
  for r in report["rounds"]:
    imagined = (f"{r['imagined_value']:.3f} | {r['gap']:+.3f}" if "imagined_value" in r
                else "not checked | ")
    lines.append(f"| {r['round']} | {r['true_value']:.3f} ± {r['true_value_stderr']:.3f} | "
                 f"{r['true_gain']:+.3f} ± {r['true_gain_stderr']:.3f} | {r['true_success']:.3f} | "
                 f"{imagined} |")
  return "\n".join(lines)
