"""A MetaWorld world model checked against the simulator, on held-out start states.

* :func:`arm_metrics` — open loop on test episodes (their recorded actions): the end effector's
  pixel error in the first view, the object's position error and the gap between the hand
  positions the two views show, read off each generated frame by the :class:`.reader.ArmReader`,
  beside copying the last context frame;
* :func:`evaluate_policies` — every policy from the same held-out start states in the simulator
  and closed loop in the world model; success in the simulator is MetaWorld's signal, in the world
  model the reader's success probability above 0.5 on any imagined frame. The policies are
  image-based on both sides (:class:`ImagePolicy`): MetaWorld's scripted expert, with Gaussian
  action noise, acting on the state the reader reads off each new frame (simulator render or
  imagined frame), the hand tracked between frames from the policy's own actions
  (:mod:`.tracking`) when a reading weight below 1 is given.

Both start each episode with ``context - 1`` idle actions so that the world model gets the
simulator's first ``context`` frames and the actions between them. Start states come from the
``evaluate`` stream (:func:`wmjax.data.synthetic.stream`), never a split's, and are checked
against every start state of the training split (:func:`held_out`).
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from wmjax.data import synthetic
from wmjax.env import WorldModelEnv
from wmjax.eval import policy_eval
from wmjax.eval.report import to_json_safe
from wmjax.eval.video import frame_grid, write_png
from wmjax.frames import to_uint8
from wmjax.progress import Progress
from wmjax.tasks.metaworld import simulator
from wmjax.tasks.metaworld.dataset import MetaWorld, MetaWorldConfig, run_episode
from wmjax.tasks.metaworld.metrics import view_metrics
from wmjax.tasks.metaworld.reader import ArmReader
from wmjax.tasks.metaworld.tracking import HandMotion, TrackedHand, fit_hand_motion

# the policies compared when none are named: the expert at four noise levels spread over the
# range of success rates (at noise 0.6 it fails as often as idle does), and standing still
DEFAULT_POLICIES = ("expert", "expert:0.2", "expert:0.3", "expert:0.4", "idle")
# how far each new reading moves the tracked hand, where a command asks for none (run.py, wmjax
# eval-policy): experiments/metaworld/RESULTS.md, "Policies that track the hand"
READING_WEIGHT = 0.3


def params_of(config) -> MetaWorldConfig:
  return MetaWorldConfig.from_dict(config.data.metaworld)


def initial_states(params: MetaWorldConfig, episodes: int, purpose: str = "evaluate",
                   seed: int = 0) -> np.ndarray:
  """``[episodes, D]`` start states drawn like the training data's, from the stream of
  ``purpose``, none equal to a training split's start state."""
  space = simulator.StartSpace.of(params.task)
  rng = synthetic.stream(params.seed, purpose, seed)
  return synthetic.unmatched_draws(lambda n: simulator.random_start_states(space, rng, n),
                                   episodes, MetaWorld.start_states(params, "train"))


def training_hand_motion(config) -> HandMotion:
  """:class:`.tracking.HandMotion` fitted on the training split of a model's dataset
  (``config.data.data_dir``), which must have been written."""
  params = params_of(config)
  builder_dir = synthetic.written_dir(MetaWorld, os.path.expanduser(config.data.data_dir), params)
  if not os.path.exists(os.path.join(builder_dir, "dataset_info.json")):
    raise FileNotFoundError(f"tracking the hand fits its motion on the model's training data, "
                            f"expected at {builder_dir}; write it with wmjax data prepare metaworld "
                            f"or give --config.data.data_dir")
  return fit_hand_motion(builder_dir)


def held_out(params: MetaWorldConfig, states) -> bool:
  """Whether none of ``states`` equals (to 1e-6) a start state of the training split."""
  return not synthetic.matching(states, MetaWorld.start_states(params, "train")).any()


def _tiled(frames: np.ndarray) -> np.ndarray:
  """``[..., V, S, S, 3]`` -> ``[..., S, V*S, 3]``: the views side by side, as the data holds them."""
  frames = np.moveaxis(frames, -4, -3)  # [..., S, V, S, 3]
  return frames.reshape(frames.shape[:-3] + (-1, frames.shape[-1]))


class ImagePolicy:
  """A simulator policy acting on the state read off frames, one episode: the reader's reading
  of each new frame goes through a :class:`.tracking.TrackedHand` (with ``reading_weight = 1``,
  the default, the newest reading alone)."""

  def __init__(self, spec: str, task: str, motion: HandMotion | None = None,
               reading_weight: float = 1.0):
    self.policy = simulator.policy_from_spec(spec, task)
    self.tracker = TrackedHand(motion, reading_weight)

  def __call__(self, reading, rng) -> np.ndarray:
    """``reading [6]`` of the newest frame -> the action ``[4]``."""
    action = self.policy(self.tracker.update(reading), rng)
    self.tracker.acted(action)
    return action


def simulate(params: MetaWorldConfig, reader: ArmReader, spec: str, states, steps: int,
             context: int, seed: int, motion: HandMotion | None = None,
             reading_weight: float = 1.0) -> dict[str, np.ndarray]:
  """:class:`ImagePolicy` ``spec`` (reading simulator frames) from each of ``states`` for
  ``context - 1`` idle then ``steps`` acting actions in the simulator: ``frames [N,
  context+steps, S, V*S, 3]``, ``actions [N, context-1+steps, 4]``, ``success [N]`` (reached at
  any step)."""
  sim = simulator.ArmSimulator(params.task, params.views, params.image_size,
                               params.action_repeat)
  frames, actions, success = [], [], []
  try:
    for n, start in enumerate(states):
      rng = np.random.default_rng([seed, n])
      policy = ImagePolicy(spec, params.task, motion, reading_weight)

      def act(t, state, views, rng):
        del state
        if t < context - 1:
          return simulator.idle(None, None)
        return policy(reader.read(_tiled(views)[None])["state"][0], rng)

      run = run_episode(sim, act, start, context - 1 + steps, rng)
      frames.append(_tiled(run["frames"]))
      actions.append(run["actions"])
      success.append(bool(run["success"].any()))
  finally:
    sim.close()
  return {"frames": np.stack(frames), "actions": np.stack(actions), "success": np.array(success)}


def imagine(model, reader: ArmReader, spec: str, start_frames, context_actions, steps: int,
            task: str, seed: int, motion: HandMotion | None = None,
            reading_weight: float = 1.0) -> np.ndarray:
  """:class:`ImagePolicy` ``spec`` closed loop in the world model (reading imagined frames) from
  ``start_frames [N, c, S, V*S, 3]`` and the ``context_actions [N, c-1, 4]`` between them: the
  frames ``[N, c+steps, S, V*S, 3]`` uint8."""
  env = WorldModelEnv.from_model(model, seed=seed)
  env.reset(start_frames, context_actions=context_actions)
  policies = [ImagePolicy(spec, task, motion, reading_weight) for _ in range(len(start_frames))]
  rngs = [np.random.default_rng([seed, n]) for n in range(len(start_frames))]
  last = to_uint8(np.asarray(start_frames)[:, -1])
  for _ in range(steps):
    states = reader.read(last)["state"]  # every episode's newest frame in one batch
    actions = np.stack([p(state, r) for p, state, r in zip(policies, states, rngs)])
    new, *_ = env.step(actions[:, None])
    last = to_uint8(np.asarray(new)[:, -1])
  return to_uint8(env.video())


def imagined_success(reader: ArmReader, frames, context: int) -> np.ndarray:
  """``[N]``: whether the reader sees success in any frame after the context."""
  n, t = frames.shape[:2]
  probability = reader.read(frames[:, context:].reshape((-1,) + frames.shape[2:]))["success"]
  return probability.reshape(n, t - context).max(1) > 0.5


def evaluate_policies(model, reader: ArmReader, out_dir: str, *, specs=DEFAULT_POLICIES,
                      episodes: int = 24, steps: int | None = None, seed: int = 0,
                      motion: HandMotion | None = None, reading_weight: float = 1.0
                      ) -> dict[str, Any]:
  """Each :class:`ImagePolicy` of ``specs`` (tracking the hand with ``motion`` and
  ``reading_weight``) from the same ``episodes`` held-out start states in the simulator and in
  the world model ``model``; writes ``policy_eval.json`` (per-episode successes on both
  sides, values, agreement with bootstrap intervals) and per policy a PNG (simulator row above
  world-model row, a few episodes) into ``out_dir``; returns the results."""
  if len(specs) < 3:  # before any simulating: the agreement needs three values on each side
    raise ValueError(f"ranking policies needs at least 3 of them, got {len(specs)}: {list(specs)}")
  params = params_of(model.config)
  context = model.config.rollout.context
  steps = steps or params.episode_length - context
  states = initial_states(params, episodes, seed=seed)
  results: dict[str, Any] = {"held_out": held_out(params, states), "episodes": episodes,
                             "steps": steps, "task": params.task, "reading_weight": reading_weight,
                             "hand_motion": motion.to_dict() if motion else None, "policies": {}}
  true_returns, estimated_returns = [], []
  os.makedirs(out_dir, exist_ok=True)
  tracker = Progress("policy evaluation (simulator and world model)", len(specs), "policies")
  for spec in specs:
    truth = simulate(params, reader, spec, states, steps, context, seed, motion, reading_weight)
    imagined = imagine(model, reader, spec, truth["frames"][:, :context],
                       truth["actions"][:, :context - 1], steps, params.task, seed, motion,
                       reading_weight)
    estimate = imagined_success(reader, imagined, context)
    true_returns.append(truth["success"].astype(np.float64))
    estimated_returns.append(estimate.astype(np.float64))
    results["policies"][spec] = {
        "simulator": policy_eval.policy_value(true_returns[-1]).to_dict(),
        "world_model": policy_eval.policy_value(estimated_returns[-1]).to_dict(),
        "simulator_success": truth["success"].astype(int).tolist(),
        "world_model_success": estimate.astype(int).tolist()}
    rows = [v for n in range(min(3, episodes)) for v in (truth["frames"][n], imagined[n])]
    write_png(os.path.join(out_dir, f"{spec.replace(':', '@')}.png"), frame_grid(rows))
    tracker.update()
  tracker.close()
  true_values = [r.mean() for r in true_returns]
  estimated_values = [r.mean() for r in estimated_returns]
  results["agreement"] = policy_eval.agreement(true_values, estimated_values)
  results["intervals"] = policy_eval.agreement_intervals(true_returns, estimated_returns)
  with open(os.path.join(out_dir, "policy_eval.json"), "w") as f:
    json.dump(to_json_safe(results), f, indent=2)
  return results


def arm_metrics(model, reader: ArmReader, frames, actions, ee_px, state, out_png: str | None = None,
                seed: int = 0) -> dict[str, Any]:
  """Open loop on recorded episodes: ``frames [N, T, S, V*S, 3]`` uint8, ``actions [N, T-1,
  4]``, the true ``ee_px [N, T, 2]`` and ``state [N, T, 6]``. The model continues from the
  first ``context`` frames with the recorded actions; per generated frame ``k`` (1 ..) the mean
  over episodes of the end effector's pixel error (reader on the generated frame against the
  truth), the object's position error (cm) and the views' hand gap (cm), with the same read off
  the last context frame (copy-last) and off the true frame (the reader's own floor). Returns
  ``{name: [T - context]}`` lists and the standard errors of the errors at the last frame."""
  context = model.config.rollout.context
  env = WorldModelEnv.from_model(model, seed=seed)
  env.reset(frames[:, :context], context_actions=actions[:, :context - 1])
  for t in range(context - 1, frames.shape[1] - 1):
    env.step(actions[:, t:t + 1])
  pred = to_uint8(env.video())
  n, t_total = frames.shape[:2]
  generated = slice(context, t_total)

  def read(video):
    out = reader.read(video[:, generated].reshape((-1,) + video.shape[2:]))
    return {k: v.reshape((n, t_total - context) + v.shape[1:]) for k, v in out.items()}

  copy = np.repeat(frames[:, context - 1:context], t_total - context, axis=1)
  result: dict[str, Any] = {}
  for name, video in (("model", pred), ("copy_last", np.concatenate(
      [frames[:, :context], copy], 1)), ("truth", frames)):
    read_out = read(video)
    ee = np.linalg.norm(read_out["ee_px"] - ee_px[:, generated], axis=-1)  # [N, T-c]
    obj = 100 * np.linalg.norm(read_out["state"][..., 3:] - state[:, generated, 3:], axis=-1)
    gap = 100 * np.linalg.norm(read_out["per_view"][..., 0, 2:5]
                               - read_out["per_view"][..., 1, 2:5], axis=-1)
    result[name] = {"ee_px_error": ee.mean(0).tolist(), "object_error_cm": obj.mean(0).tolist(),
                    "view_hand_gap_cm": gap.mean(0).tolist(),
                    "ee_px_error_stderr": (ee.std(0, ddof=1) / np.sqrt(n)).tolist(),
                    **{k: v.mean(0).tolist() for k, v in view_metrics(
                        video[:, generated], frames[:, generated], {}).items() if "mse" in k}}
  if out_png:
    rows = [v for i in range(min(4, n)) for v in (frames[i], pred[i])]
    write_png(out_png, frame_grid(rows))
  return result
