"""A Push-T world model checked against the gym-pusht simulator.

* :func:`evaluate_policies` — every policy runs from the same initial states both in the
  simulator (ground truth: the simulator's final coverage) and closed loop in the world model
  (estimate: a reward function on the imagined frames); values, agreement table, videos.
* :func:`plan_in_simulator` — model-predictive control by ranking (:mod:`wmjax.eval.planning`)
  executed in the simulator for several candidate counts ``K``; final coverage per ``K``.
* :func:`summarize` — the headline figures of both: correlations, whether the ranking matches,
  and per ``K`` the final coverage and its paired gain over ``K = 1``.

Both start each episode from :func:`.simulator.random_initial_states` (the training data's
distribution) with ``context - 1`` still steps, so the world model gets the same first ``context``
frames and the (known) actions between them as the simulator. The start states are held out by
construction: policy evaluation and planning draw them from their own random streams
(:func:`wmjax.data.synthetic.stream`), and both check them against every start state of the
training split (:func:`held_out`) and report the result as ``held_out``.
"""

from __future__ import annotations

import json
import os
from typing import Any

import jax
import numpy as np

from wmjax.data import synthetic
from wmjax.env import RewardFn, WorldModelEnv
from wmjax.eval import planning, policy_eval
from wmjax.eval.video import (VIDEO_FORMATS, comparison, frame_grid, stack_rows, write_png,
                              write_video)
from wmjax.frames import to_uint8
from wmjax.progress import Progress
from wmjax.tasks.pusht import simulator as pusht
from wmjax.tasks.pusht.dataset import INSTRUCTION, PushT, PushTConfig
from wmjax.tasks.pusht.metrics import pusht_metrics

# the T's frame metrics followed through closed-loop rollouts (``wmjax.tasks.pusht.metrics``)
BLOCK_METRICS = ("block_error_px", "block_angle_error_deg", "block_iou")


def _params(config) -> PushTConfig:
  return PushTConfig.from_dict(config.data.get("pusht") or {})  # defaults where not Push-T


def initial_states(config, episodes: int, purpose: str, seed: int = 0) -> np.ndarray:
  """``[episodes, 5]`` simulator states drawn like the config's training data, from the stream
  of ``purpose`` (``evaluate`` or ``plan``; ``seed`` picks one of its draws), which no split of
  the dataset draws from."""
  params = _params(config)
  rng = synthetic.stream(params.seed, purpose, seed)
  return pusht.random_initial_states(rng, episodes, max_offset=params.max_offset,
                                     max_angle=params.max_angle)


def held_out(config, states) -> bool | None:
  """Whether none of ``states [N, 5]`` equals (to 1e-6) a start state of the config's training
  split, replayed from its parameters (:meth:`.dataset.PushT.start_states`); None where the
  config's dataset is not the generated Push-T one."""
  if config.data.dataset != "pusht":
    return None
  return not synthetic.matching(states, PushT.start_states(_params(config), "train")).any()


def policy_chunk(config) -> int:
  """Actions a Push-T policy returns per call: the chunk the config's dataset was collected
  with, whatever the model's block length (``rollout.horizon``)."""
  return PushTConfig.from_dict(config.data.get("pusht") or {}).chunk


def actions_for(config, control_steps: int) -> int:
  """Actions that take ``control_steps`` control steps of 0.1 s with the config's dataset, each
  action held for ``data.pusht.action_repeat`` of them (at least one action)."""
  return _params(config).actions_for(control_steps)


def _image_size(model) -> int:
  h, w, _ = model.image_shape
  if h != w:
    raise ValueError(f"a Push-T model has square frames, got {model.image_shape}")
  return h


# the policies ``wmjax eval-policy`` compares when none are named: noise levels of the scripted
# pusher, and standing still
DEFAULT_POLICIES = ("push", "push:0.1", "push:0.2", "push:0.5", "stay")


def policies_from_specs(specs, chunk: int) -> dict[str, pusht.PolicyFn]:
  """Policies by spec (:func:`.simulator.policy_from_spec`; default :data:`DEFAULT_POLICIES`),
  each acting ``chunk`` steps at a time, named as files may be (``push:0.1`` -> ``push@0.1``)."""
  return {spec.replace(":", "@"): pusht.policy_from_spec(spec, chunk)
          for spec in specs or DEFAULT_POLICIES}


def proposal_from_spec(spec: str, length: int) -> planning.Proposal:
  """The planning proposal sampling candidates of ``length`` actions from the policy ``spec``."""
  return planning.policy_proposal(pusht.policy_from_spec(spec, length))


def simulate_and_imagine(model, policy: pusht.PolicyFn, states, steps: int,
                         policy_key: jax.Array, rollout_key: jax.Array, *, scan: bool = False
                         ) -> tuple[dict[str, np.ndarray], np.ndarray]:
  """``policy`` from ``states [N, 5]`` for ``steps`` actions in the simulator (after
  ``rollout.context - 1`` still steps), and closed loop in the world model ``model`` from the
  simulator's first ``context`` frames and the actions between them: ``(truth, imagined)``,
  ``truth`` as :func:`.simulator.simulate_policy` returns it, ``imagined [N, context+steps, H, W,
  3]`` RGB frames. ``policy_key`` draws the policy's noise in both, ``rollout_key`` the model's
  samples; ``scan``: roll out inside one jitted scan (pure-JAX policies only), else step
  :class:`wmjax.env.WorldModelEnv`."""
  config = model.config
  c, h = config.rollout.context, config.rollout.horizon
  truth = pusht.simulate_policy(policy, states, steps, image_size=_image_size(model),
                                key=policy_key, context=c,
                                action_repeat=_params(config).action_repeat)
  start, known = truth["frames"][:, :c], truth["actions"][:, :c - 1]
  if scan:
    imagined = policy_eval.scan_episodes(
        model.world_model, model.params, policy, start, steps, rollout_key,
        policy_key, horizon=h, action_stats=model.action_stats,
        normalization=config.data.normalization, codec=model.codec, context_actions=known)
    return truth, np.asarray(imagined["frames"])
  env = WorldModelEnv.from_model(model, seed=rollout_key)
  return truth, policy_eval.env_episodes(env, policy, start, steps, policy_key,
                                         context_actions=known)["frames"]


def evaluate_policies(model, policies: dict[str, pusht.PolicyFn],
                      rewards: dict[str, RewardFn], *, episodes: int, steps: int, seed: int = 0,
                      scan: bool = False, out: str | None = None, videos: int = 4,
                      video_format: str = "mp4") -> dict[str, Any]:
  """Values of ``policies`` in the simulator and in the world model ``model`` (a
  :class:`wmjax.model.LoadedModel`), and their agreement, for every reward function
  in ``rewards`` (all scored on the same rollouts). With ``out``, ``videos`` episodes per policy
  are written to ``out/videos/POLICY.VIDEO_FORMAT`` (``mp4`` or ``gif``: simulator | world
  model | difference) and ``out/videos/POLICY.png`` (a frame grid, the simulator's row above the
  world model's, every policy chunk's first frame).

  Per policy: ``simulator`` (true final coverage) and, per reward, ``simulator_reward`` (the
  reward on the simulator's frames: what a perfect world model would score) and ``world_model``
  (the reward on the imagined frames), each mean ± standard error over ``episodes``. Per reward,
  ``agreement`` compares the world model's values with the simulator's and
  ``agreement_same_reward`` with ``simulator_reward``. ``scan``: roll out inside one jitted scan
  (pure-JAX policies only)."""
  if f".{video_format}" not in VIDEO_FORMATS:
    raise ValueError(f"video_format must be 'mp4' or 'gif', got {video_format!r}")
  if len(policies) < 3 or not rewards:
    raise ValueError(f"need at least 3 policies and a reward, got {len(policies)} policies and "
                     f"{len(rewards)} rewards")
  config = model.config
  c = config.rollout.context
  states = initial_states(config, episodes, "evaluate", seed)
  names, values, block, videos_written = list(policies), {}, {}, {}
  tracker = Progress("policy evaluation (simulator and world model)", len(names), "policies")
  for index, name in enumerate(names):
    truth, imagined = simulate_and_imagine(
        model, policies[name], states, steps, jax.random.fold_in(jax.random.key(seed), index),
        jax.random.fold_in(jax.random.key(seed + 1), index), scan=scan)
    values[name] = {"simulator": policy_eval.policy_value(truth["coverage"][:, -1])}
    for reward, reward_fn in rewards.items():
      values[name][reward] = {
          "simulator_reward": policy_eval.policy_value(policy_eval.episode_returns(
              truth["frames"], reward_fn, INSTRUCTION, start=c - 1)),
          "world_model": policy_eval.policy_value(policy_eval.episode_returns(
              imagined, reward_fn, INSTRUCTION, start=c - 1))}
    block[name] = rollout_block_metrics(imagined, truth["frames"], c)
    if out and videos:
      shown = range(min(videos, episodes))
      rows = [comparison(truth["frames"][i], imagined[i]) for i in shown]
      videos_written[name] = write_video(os.path.join(out, "videos", f"{name}.{video_format}"),
                                         stack_rows(rows))
      # every chunk's first frame: simulator above world model, two rows per episode
      every = slice(c - 1, None, policy_chunk(config))
      write_png(os.path.join(out, "videos", f"{name}.png"), frame_grid(
          [video[every] for i in shown for video in (truth["frames"][i], imagined[i])]))
    tracker.update()
  tracker.close()

  simulator = [values[n]["simulator"] for n in names]
  result = {"policies": {n: {"simulator": _value_dict(values[n]["simulator"]),
                             "block": block[n]} for n in names},
            "rewards": {}, "episodes": episodes, "steps": steps, "seed": seed,
            "held_out": held_out(config, states), "videos": videos_written}
  for reward in rewards:
    model_values = [values[n][reward]["world_model"] for n in names]
    same_reward = [values[n][reward]["simulator_reward"] for n in names]
    for n in names:
      result["policies"][n][reward] = {k: _value_dict(v) for k, v in values[n][reward].items()}
    agreement = policy_eval.agreement([v.mean for v in simulator],
                                      [v.mean for v in model_values])
    agreement_same = policy_eval.agreement([v.mean for v in same_reward],
                                           [v.mean for v in model_values])
    result["rewards"][reward] = {
        "agreement": agreement, "agreement_same_reward": agreement_same,
        "agreement_ci95": policy_eval.agreement_intervals(
            [v.returns for v in simulator], [v.returns for v in model_values], seed=seed),
        "table": policy_eval.agreement_table(names, simulator, model_values, agreement),
        "table_same_reward": policy_eval.agreement_table(names, same_reward, model_values,
                                                         agreement_same)}
  if out:
    _write(out, "policy_eval", result, policy_report(result))
  return result


def _value_dict(value: policy_eval.PolicyValue) -> dict:
  """A policy value with its per-episode returns (the episodes are the same start states for
  every policy, so values can be paired and resampled later)."""
  return {**value.to_dict(), "per_episode": [float(x) for x in value.returns]}


def rollout_block_metrics(imagined, truth, context: int) -> dict[str, dict]:
  """The T in closed-loop rollouts against the simulator's ``truth [B, T, S, S, 3]``, per
  generated step, for the world model's frames ``imagined`` (the same shape, the first
  ``context`` given) and for copying the last given frame (a model that never moves the T):
  per kind, the mean over episodes of each of :data:`BLOCK_METRICS` per step (``per_step``:
  ``[T - context]`` lists) and at the last step (``end``), and each episode's value at the last
  step (``end_per_episode``: ``[B]`` lists, in the order of the start states, so that two models
  or samplers can be compared episode by episode)."""
  truth = to_uint8(truth)
  copy = np.repeat(truth[:, context - 1:context], truth.shape[1] - context, axis=1)
  rows = {}
  for kind, frames in (("world_model", to_uint8(imagined)[:, context:]),
                       ("copy_first_frame", copy)):
    scores = pusht_metrics(frames, truth[:, context:], {})
    per_step = {m: [float(x) for x in scores[m].mean(0)] for m in BLOCK_METRICS}
    rows[kind] = {"per_step": per_step, "end": {m: v[-1] for m, v in per_step.items()},
                  "end_per_episode": {m: [float(x) for x in scores[m][:, -1]]
                                      for m in BLOCK_METRICS}}
  return rows


def policy_report(result: dict) -> str:
  """Markdown: whether the start states were held out; per reward, the agreement tables of
  :func:`evaluate_policies` with bootstrap intervals; the T at the end of the rollouts."""
  parts = [f"Start states held out from the training split: {result['held_out']}", ""]
  for reward, tables in result["rewards"].items():
    ci = tables["agreement_ci95"]
    parts += [f"## Reward: {reward}", "", "World model against the simulator's true coverage:", "",
              tables["table"], "",
              "95 % bootstrap intervals over episodes (resampled within policy, "
              f"{ci['samples']} draws): " + ", ".join(
                  f"{name} {_interval(ci[name])}" for name in ("pearson", "spearman")),
              "", f"World model against {reward} on the simulator's frames:", "",
              tables["table_same_reward"], ""]
  parts += ["## The T at the last step (mean over episodes)", "",
            "| policy | " + " | ".join(f"{m} (model / copy first frame)" for m in BLOCK_METRICS)
            + " |", "|---" * (len(BLOCK_METRICS) + 1) + "|"]
  for name, values in result["policies"].items():
    model, copy = values["block"]["world_model"]["end"], values["block"]["copy_first_frame"]["end"]
    parts.append(f"| {name} | " + " | ".join(f"{model[m]:.2f} / {copy[m]:.2f}"
                                            for m in BLOCK_METRICS) + " |")
  return "\n".join(parts) + "\n"


def _interval(bounds) -> str:
  return "undefined" if bounds is None else f"[{bounds[0]:.3f}, {bounds[1]:.3f}]"


class SimulatorLookahead(planning.Planner):
  """Ranks candidates by running them in copies of the simulator reset to the environments'
  current poses (velocities zeroed): the choice a perfect world model would make, as a
  reference for the world model's planner."""

  def __init__(self, sim: pusht.PushTSimulator, proposal, value_fn, num_candidates: int,
               horizon: int):
    super().__init__(None, None, proposal, value_fn, num_candidates, horizon,
                     instruction=INSTRUCTION)
    self.sim = sim
    self._lookahead = None

  def imagine(self, frames, context_actions, candidates, rng):
    del context_actions, rng
    candidates = np.asarray(candidates)
    b, k, n = candidates.shape[:3]
    if self._lookahead is None:
      self._lookahead = pusht.PushTSimulator(b * k, self.sim.image_size, self.sim.action_repeat)
    frame, _ = self._lookahead.reset(np.repeat(self.sim.reset_states(), k, axis=0))
    rollout = [np.repeat(np.asarray(frames, np.uint8)[:, :-1], k, axis=0), frame[:, None]]
    for t in range(n):
      rollout.append(self._lookahead.step(candidates[:, :, t].reshape(b * k, 2))[0][:, None])
    video = np.concatenate(rollout, 1)
    return video.reshape((b, k) + video.shape[1:])


def plan_in_simulator(model, proposal: planning.Proposal, value_fn: RewardFn,
                      candidates: list[int], *, episodes: int, steps: int, seed: int = 0,
                      execute: int | None = None, lookahead: bool = False,
                      out: str | None = None) -> dict[str, Any]:
  """Final simulator coverage of model-predictive control with ``K`` candidates per replanning,
  for each ``K`` in ``candidates`` (``K = 1``: the proposal alone), from the same states;
  ``lookahead`` adds the same control with :class:`SimulatorLookahead` in place of the world
  model, for reference. ``execute``: actions run before replanning (default: the Push-T policy
  chunk, :func:`policy_chunk`).

  Exploitability: the world-model planner also imagines the single candidate of ``K = 1``, and
  for every ``K`` the row keeps ``imagined_value`` (``value_fn`` on the chosen plan's last
  imagined frame) beside ``simulator_value`` (``value_fn`` on the simulator's frame after that
  plan ran), averaged over the replannings of each episode and then over episodes (standard
  errors clustered by episode: the replannings of one episode are not independent);
  ``exploitability_gap`` is their paired difference, with ``per_episode`` values so that gaps of
  two ``K`` can be paired (:func:`summarize`). A planner that picks the candidates whose imagined
  outcome the model gets most wrong opens this gap as ``K`` grows.

  The start states come from the ``plan`` stream (:func:`initial_states`); ``held_out`` says
  whether none of them is a training start state."""
  config = model.config
  c, h = config.rollout.context, config.rollout.horizon
  execute = execute or policy_chunk(config)
  size = _image_size(model)
  states = initial_states(config, episodes, "plan", seed)
  rows = {}
  planners = ["world_model"] + (["simulator"] if lookahead else [])
  tracker = Progress("planning", len(candidates) * len(planners), "settings of K and planner")
  for k in candidates:
    rows[k] = {}
    for kind in planners:
      sim = pusht.PushTSimulator(episodes, size, _params(config).action_repeat)
      if kind == "world_model":
        planner = planning.Planner(
            model.world_model, model.params, proposal, value_fn, num_candidates=k, horizon=h,
            action_stats=model.action_stats, normalization=config.data.normalization,
            codec=model.codec, instruction=INSTRUCTION, score_single=True)
      else:
        planner = SimulatorLookahead(sim, proposal, value_fn, k, h)
      frames, known, _ = sim.start(states, c)
      coverage = []

      def step_fn(action, sim=sim, coverage=coverage):
        frame, step_info = sim.step(action)
        coverage.append(step_info["coverage"])
        return frame

      run = planning.run_closed_loop(
          planner, step_fn, np.stack(frames, 1), steps, jax.random.key(seed + 7),
          context_actions=np.stack(known, 1) if known else None, execute=execute, context=c)
      final = policy_eval.policy_value(coverage[-1])
      rows[k][kind] = {"final_coverage": final.to_dict(), "replans": len(run["plans"]),
                       "per_episode": [float(x) for x in coverage[-1]]}
      if kind == "world_model":
        rows[k][kind].update(_exploitability(run, value_fn, c, execute, steps))
      tracker.update()
  tracker.close()
  result = {"candidates": rows, "episodes": episodes, "steps": steps, "seed": seed,
            "execute": execute, "held_out": held_out(config, states),
            "table": planning_table(rows)}
  if out:
    _write(out, "plan", result, result["table"] + "\n")
  return result


def _exploitability(run: dict, value_fn: RewardFn, context: int, execute: int,
                    steps: int) -> dict[str, Any]:
  """The chosen plans' imagined values beside ``value_fn`` on the simulator's frame after each
  plan ran, per episode averaged over its replannings (see :func:`plan_in_simulator`)."""
  imagined, real = [], []
  for i, plan in enumerate(run["plans"]):
    after = context - 1 + min((i + 1) * execute, steps)  # the frame the plan's last action made
    b = len(plan.index)
    imagined.append(plan.scores[np.arange(b), plan.index])
    real.append(np.asarray(value_fn(run["frames"][:, after:after + 1], INSTRUCTION)))
  imagined, real = np.mean(imagined, axis=0), np.mean(real, axis=0)  # [episodes]
  return {"imagined_value": _value_dict(policy_eval.policy_value(imagined)),
          "simulator_value": _value_dict(policy_eval.policy_value(real)),
          "exploitability_gap": _value_dict(policy_eval.policy_value(imagined - real))}


def planning_table(rows: dict[int, dict]) -> str:
  """Markdown: final simulator coverage (mean ± stderr) per K and planner."""
  kinds = list(next(iter(rows.values())))
  titles = {"world_model": "world-model planner", "simulator": "simulator lookahead"}
  lines = ["| K | " + " | ".join(titles[k] for k in kinds) + " |", "|---" * (len(kinds) + 1) + "|"]
  for k, row in rows.items():
    cells = [f"{row[kind]['final_coverage']['mean']:.3f} ± "
             f"{row[kind]['final_coverage']['stderr']:.3f}" for kind in kinds]
    lines.append(f"| {k} | " + " | ".join(cells) + " |")
  return "\n".join(lines)


def summarize(policy_result: dict, plan_result: dict, reward: str = "coverage") -> dict[str, Any]:
  """The headline figures of a policy evaluation (:func:`evaluate_policies`) and a planning run
  (:func:`plan_in_simulator`, or several merged, with ``K = 1`` among them).

  ``held_out``: True only where both checked their start states against the training split's
  and found none of them there. ``pearson`` / ``spearman`` / ``kendall`` and
  ``ranking_matches``: the world model's values (``reward`` on the imagined frames) against the
  simulator's true final coverage over the policies (NaN correlations become None), with
  ``pearson_ci95`` / ``spearman_ci95`` (bootstrap over episodes, resampled within policy);
  ``policies``: each policy's values with their standard errors and the T at the last step
  (world model and copy-first-frame); ``block_iou_push_end`` (and ``..._copy_first_frame``): the
  T's IoU at the last step of the ``push`` rollouts, where that policy was evaluated.
  ``planning`` (and ``planning_lookahead`` when the simulator planned too), keyed by K as a
  string: final coverage ``mean`` / ``stderr`` over the episodes and the paired ``gain_mean`` /
  ``gain_stderr`` over K = 1 from the same initial states, with the episodes it made ``better``
  and ``worse``; for the world model the chosen plans' ``imagined_value``, ``simulator_value``
  and ``exploitability_gap`` (standard errors clustered by episode) and ``selection_effect``: the
  gap minus K = 1's in the same episode (K = 1's gap is the model's own bias, which choosing
  among candidates did not cause)."""
  if reward not in policy_result["rewards"]:
    raise ValueError(f"reward {reward!r} was not evaluated; the policy evaluation has "
                     f"{sorted(policy_result['rewards'])}")
  agreement = policy_result["rewards"][reward]["agreement"]
  intervals = policy_result["rewards"][reward]["agreement_ci95"]
  rows = {str(k): row for k, row in plan_result["candidates"].items()}
  if "1" not in rows:
    raise ValueError(f"planning gains are measured over K = 1, which was not run (K in "
                     f"{sorted(rows, key=int)})")

  def finite(x):
    return None if x is None or not np.isfinite(x) else float(x)

  def paired(values, base):
    values, base = np.asarray(values), np.asarray(base)
    if values.shape != base.shape:
      raise ValueError(f"{values.size} episodes against K = 1's {base.size}: the gains pair "
                       f"episodes from the same initial states")
    return policy_eval.policy_value(values - base)

  def gains(kind):
    base = rows["1"][kind]["per_episode"]
    table = {}
    for k in sorted(rows, key=int):
      final = np.asarray(rows[k][kind]["per_episode"])
      value, gain = policy_eval.policy_value(final), paired(final, base)
      table[k] = {"mean": value.mean, "stderr": value.stderr, "gain_mean": gain.mean,
                  "gain_stderr": gain.stderr, "better": int((final > np.asarray(base)).sum()),
                  "worse": int((final < np.asarray(base)).sum())}
      for name in ("imagined_value", "simulator_value", "exploitability_gap"):
        if name in rows[k][kind]:
          table[k][name] = rows[k][kind][name]["mean"]
          table[k][f"{name}_stderr"] = rows[k][kind][name]["stderr"]
      if "exploitability_gap" in rows[k][kind]:
        effect = paired(rows[k][kind]["exploitability_gap"]["per_episode"],
                        rows["1"][kind]["exploitability_gap"]["per_episode"])
        table[k].update(selection_effect=effect.mean, selection_effect_stderr=effect.stderr)
    return table

  policies = {}
  for name, values in policy_result["policies"].items():
    policies[name] = {"simulator": values["simulator"]["mean"],
                      "simulator_stderr": values["simulator"]["stderr"],
                      "world_model": values[reward]["world_model"]["mean"],
                      "world_model_stderr": values[reward]["world_model"]["stderr"],
                      "block_end": {kind: values["block"][kind]["end"]
                                    for kind in ("world_model", "copy_first_frame")}}
  summary = {
      "held_out": policy_result.get("held_out") is True and plan_result.get("held_out") is True,
      "reward": reward, "pearson": finite(agreement["pearson"]),
      "pearson_ci95": intervals["pearson"], "spearman": finite(agreement["spearman"]),
      "spearman_ci95": intervals["spearman"], "kendall": finite(agreement["kendall"]),
      "ranking_matches": agreement["ranking_preserved"] == 1.0, "policies": policies,
      "episodes": {"policy_eval": policy_result["episodes"], "plan": plan_result["episodes"]},
      "planning": gains("world_model")}
  if "push" in policies:
    for kind, suffix in (("world_model", ""), ("copy_first_frame", "_copy_first_frame")):
      summary[f"block_iou_push_end{suffix}"] = policies["push"]["block_end"][kind]["block_iou"]
  if all("simulator" in row for row in rows.values()):
    summary["planning_lookahead"] = gains("simulator")
  return summary


def _write(out: str, name: str, result: dict, report: str) -> None:
  os.makedirs(out, exist_ok=True)
  with open(os.path.join(out, f"{name}.json"), "w") as f:
    json.dump(result, f, indent=2)
  with open(os.path.join(out, f"{name}.md"), "w") as f:
    f.write(report)
