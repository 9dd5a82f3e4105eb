"""Where closed-loop policy evaluation in a MetaWorld world model goes wrong: the model, or the
policy reading its frames.

For each policy, from the same held-out start states as ``run.py``'s policy stage: the
simulator's episodes (the image-based policy acting on simulator frames), then the world model
fed those episodes' actions **open loop**, then the policy **closed loop** in the world model.
For each of the three: success (the reader's, on any frame after the context; also as each
view alone reads it, and, for a task whose simulator judges success by the object's place, that
rule applied to the object the reader reads), the length of
the hand's path (cm) and its distance from the simulator's hand at every step (cm), all read by
the reader; and, open loop, each view's reading of the hand and the object against the same
view of the simulator's frames. Success open loop near the simulator's and far from it closed
loop puts the fault in the loop (what the policy reads off imagined frames), not in the model's
response to actions.

``--policy_view V`` makes the policies read the hand and the object from view ``V`` alone (on
both sides; success is still read from every view). Writes ``--out`` (JSON) and prints a line per
policy.

    python experiments/metaworld/closed_loop.py --model W/model --reader W/reader --out cl.json
"""

from __future__ import annotations

import argparse
import json

import numpy as np


class OneViewReader:
  """An :class:`~wmjax.tasks.metaworld.reader.ArmReader` whose fused ``state`` is one view's."""

  def __init__(self, reader, view: int):
    self.reader, self.view = reader, view

  def __getattr__(self, name):
    return getattr(self.reader, name)

  def read(self, frames, batch: int = 512):
    out = self.reader.read(frames, batch)
    out["state"] = out["per_view"][:, self.view, 2:]
    return out


# tasks whose success the simulator decides by where the object is: (offset of the goal from the
# object's start placement, radius) -- metaworld's SawyerDrawerOpenEnvV3, the handle within 3 cm
OBJECT_GOALS = {"drawer-open-v3": (np.array([0.0, -0.36, 0.09]), 0.03)}


def success_from_object(objects, start_states, task: str, context: int) -> float:
  """Objects read ``[N, T, 3]`` -> the share of episodes whose read object comes within the
  task's radius of its goal (its start placement ``start_states[:, 3:6]`` plus the offset) on
  some frame after the ``context``: the simulator's own rule applied to the reader's reading."""
  offset, radius = OBJECT_GOALS[task]
  goal = np.asarray(start_states)[:, 3:6] + offset
  distance = np.linalg.norm(objects[:, context:] - goal[:, None], axis=-1)
  return float((distance.min(1) <= radius).mean())


def success_per_view(reader, frames, context: int) -> list[float]:
  """Frames ``[N, T, S, V*S, 3]`` -> for each view, the share of episodes whose view alone shows
  success on some frame after the ``context``."""
  n, t = frames.shape[:2]
  after = frames[:, context:].reshape((-1,) + frames.shape[2:])
  probability = reader.read(after)["success_per_view"].reshape(n, t - context, reader.views)
  return (probability.max(1) > 0.5).mean(0).tolist()


def hand_and_object(reader, frames) -> tuple[np.ndarray, np.ndarray]:
  """Frames ``[N, T, S, V*S, 3]`` -> fused state ``[N, T, 6]`` and per view ``[N, T, V, 6]``."""
  n, t = frames.shape[:2]
  read = reader.read(frames.reshape((-1,) + frames.shape[2:]))
  return (read["state"].reshape(n, t, -1),
          read["per_view"][..., 2:].reshape(n, t, reader.views, -1))


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--model", required=True, help="a MetaWorld training workdir")
  parser.add_argument("--reader", required=True, help="a fitted reader's directory")
  parser.add_argument("--out", required=True, help="the JSON to write")
  parser.add_argument("--policies", default="expert,expert:0.4")
  parser.add_argument("--episodes", type=int, default=24)
  parser.add_argument("--policy_view", type=int, default=None,
                      help="the policies read the state from this view alone")
  parser.add_argument("--reading_weight", type=float, default=1.0,
                      help="the policies track the hand (wmjax.tasks.metaworld.tracking), its "
                           "motion fitted on the model's training data")
  parser.add_argument("--override", action="append", default=[],
                      help="an inference setting of the model, dotted.key=value (e.g. "
                           "sampling.num_steps=32), repeatable")
  parser.add_argument("--seed", type=int, default=0,
                      help="the world model's sampling seed (the simulator's episodes keep seed 0)")
  args = parser.parse_args(argv)

  from wmjax.env import WorldModelEnv
  from wmjax.frames import to_uint8
  from wmjax.model import load_model
  from wmjax.tasks.metaworld import evaluate
  from wmjax.tasks.metaworld.reader import ArmReader

  model = load_model(args.model, overrides=args.override)
  reader = ArmReader.load(args.reader)
  policy_reader = reader if args.policy_view is None else OneViewReader(reader, args.policy_view)
  params = evaluate.params_of(model.config)
  context = model.config.rollout.context
  steps = params.episode_length - context
  states = evaluate.initial_states(params, args.episodes)
  weight = args.reading_weight
  motion = evaluate.training_hand_motion(model.config) if weight < 1 else None
  results = {"model": args.model, "reader": args.reader, "overrides": args.override,
             "seed": args.seed, "policy_view": args.policy_view,
             "reading_weight": weight,
             "episodes": args.episodes, "steps": steps, "policies": {}}
  for spec in args.policies.split(","):
    truth = evaluate.simulate(params, policy_reader, spec, states, steps, context, 0, motion,
                              weight)
    env = WorldModelEnv.from_model(model, seed=args.seed)
    env.reset(truth["frames"][:, :context], context_actions=truth["actions"][:, :context - 1])
    for t in range(steps):
      env.step(truth["actions"][:, context - 1 + t][:, None])
    open_loop = to_uint8(env.video())
    closed_loop = evaluate.imagine(model, policy_reader, spec, truth["frames"][:, :context],
                                   truth["actions"][:, :context - 1], steps, params.task,
                                   args.seed, motion, weight)
    videos = {"simulator": truth["frames"], "open_loop": open_loop, "closed_loop": closed_loop}
    readings = {name: hand_and_object(reader, frames) for name, frames in videos.items()}
    true_state, true_views = readings["simulator"]
    rows = {"simulator_success": float(truth["success"].mean())}
    for name, frames in videos.items():
      state, views = readings[name]
      gap = np.linalg.norm(state[..., :3] - true_state[..., :3], axis=-1) * 100
      rows[name] = {
          "success": float(evaluate.imagined_success(reader, frames, context).mean()),
          "success_per_view": success_per_view(reader, frames, context),
          "hand_path_cm": float(np.linalg.norm(np.diff(state[..., :3], axis=1), axis=-1)
                                .sum(1).mean() * 100),
          "hand_from_simulator_cm": gap.mean(0).round(2).tolist()}
      if params.task in OBJECT_GOALS:
        rows[name]["success_from_object"] = success_from_object(state[..., 3:], states,
                                                                params.task, context)
        rows[name]["success_from_object_per_view"] = [
            success_from_object(views[:, :, v, 3:], states, params.task, context)
            for v in range(reader.views)]
      if name == "open_loop":
        after = slice(context, None)
        rows[name]["per_view_error_cm"] = [
            {"hand": float(np.linalg.norm(views[:, after, v, :3] - true_views[:, after, v, :3],
                                          axis=-1).mean() * 100),
             "object": float(np.linalg.norm(views[:, after, v, 3:] - true_views[:, after, v, 3:],
                                            axis=-1).mean() * 100)}
            for v in range(reader.views)]
        rows[name]["fused_hand_error_cm"] = float(gap[:, after].mean())
    results["policies"][spec] = rows
    print(spec, json.dumps({k: (v if not isinstance(v, dict) else
                                {kk: vv for kk, vv in v.items() if kk != "hand_from_simulator_cm"})
                            for k, v in rows.items()}), flush=True)
  with open(args.out, "w") as f:
    json.dump(results, f, indent=1)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
