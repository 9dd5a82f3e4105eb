"""Push-T: does planning gain with a model that reads the exact state, at the world model's budget?

Goal 4 asks planning in the 2-core world model to gain over K = 1 at K = 10 and K = 50; the
world model gains a little at K = 10 and nothing at K = 50, where the planner picks the
candidates it overvalues. This runs the same protocol as ``wmjax plan`` (its held-out start
states, the ``push:0.2`` proposal, K candidates of one action ranked by the ``coverage`` reward of
the imagined frame, the best executed in the simulator, replanning after each action) with the
learner of ``contact_from_state.py`` as the planner's model: an MLP for the T's next pose and
one for the agent's, trained on the profile's data at the world model's budget, each predicted
state drawn by the simulator's own renderer. Its inputs are the simulator's exact state (or,
with ``--perceived``, the state read off the frames). If such a planner gains at K = 50, the
world model's planner fails for the world model's errors; if it does not, the budget is short
for any model of this kind.

    python experiments/pusht/plan_with_learner.py --data W/data/pusht/NAME/1.0.0 \\
        --config configs/pusht.py:latent [--perceived] --seed S --out P.json
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from contact_from_state import (agent_targets, draw_states, fit_selected, predicted_state,
                                read_split, seen_states, transitions)
from wmjax.config import load_config
from wmjax.eval import planning, policy_eval
from wmjax.eval.rewards import reward_from_spec
from wmjax.tasks.pusht import evaluate
from wmjax.tasks.pusht.dataset import PushTConfig
from wmjax.tasks.pusht.simulator import PushTSimulator


class LearnerLookahead(planning.Planner):
  """Ranks candidates by the learner's prediction of the state each leads to, drawn by the
  simulator's renderer. ``states_of(frames [B, c, H, W, 3]) -> [B, c, 5]``: the states the
  learner reads (exact or read off the frames)."""

  def __init__(self, predict, predict_agent, states_of, proposal, value_fn, num_candidates: int,
               horizon: int, image_size: int, action_repeat: int):
    super().__init__(None, None, proposal, value_fn, num_candidates, horizon,
                     instruction=evaluate.INSTRUCTION, score_single=True)
    self.predict, self.predict_agent, self.states_of = predict, predict_agent, states_of
    self.image_size, self.action_repeat = image_size, action_repeat
    self._renderer = None

  def _draw(self, states: np.ndarray) -> np.ndarray:
    if self._renderer is None or len(self._renderer.envs) != len(states):
      self._renderer = PushTSimulator(len(states), self.image_size, self.action_repeat)
    return draw_states(self._renderer, states)

  def imagine(self, frames, context_actions, candidates, rng):
    del rng
    frames, candidates = np.asarray(frames, np.uint8), np.asarray(candidates, np.float64)
    b, k, n = candidates.shape[:3]
    states = np.repeat(self.states_of(frames)[:, -2:], k, axis=0)  # [B*K, 2, 5]
    seen = [states[:, 0], states[:, 1]]
    taken = [np.repeat(np.asarray(context_actions, np.float64)[:, -1], k, axis=0)]
    drawn = []
    for t in range(n):
      taken.append(candidates[:, :, t].reshape(b * k, 2))
      seen.append(predicted_state(self.predict, self.predict_agent, seen[-2], seen[-1],
                                  taken[-2], taken[-1]))
      drawn.append(self._draw(seen[-1])[:, None])
    video = np.concatenate([np.repeat(frames, k, axis=0)] + drawn, 1)
    return video.reshape((b, k) + video.shape[1:])


def plan(predict, predict_agent, config, candidates: list[int], episodes: int, seed: int,
         perceived: bool) -> dict:
  """Final coverage per K of :class:`LearnerLookahead` control (``predict=None``: the
  simulator's own lookahead, the reference) from the ``plan`` stream's start states, as
  :func:`wmjax.tasks.pusht.evaluate.plan_in_simulator` runs the world model's planner, with its
  paired gain over K = 1 and the imagined value of the chosen plans."""
  params = PushTConfig.from_dict(config.data.pusht)
  c, chunk = config.rollout.context, evaluate.policy_chunk(config)
  steps = params.actions_for(24)
  states = evaluate.initial_states(config, episodes, "plan", seed)
  if not evaluate.held_out(config, states):
    raise ValueError("the planning start states meet the training split")
  value_fn = reward_from_spec("coverage")
  rows, base = {}, None
  for k in candidates:
    sim = PushTSimulator(episodes, params.image_size, params.action_repeat)
    frames, known, infos = sim.start(states, c)
    history, coverage = [i["state"].astype(np.float64) for i in infos], []

    def step_fn(action, sim=sim, history=history, coverage=coverage):
      frame, info = sim.step(action)
      history.append(info["state"].astype(np.float64))
      coverage.append(info["coverage"])
      return frame

    def states_of(window, history=history):
      return seen_states(window) if perceived else np.stack(history[-window.shape[1]:], 1)

    proposal = evaluate.proposal_from_spec("push:0.2", chunk)
    planner = (evaluate.SimulatorLookahead(sim, proposal, value_fn, k, 1) if predict is None else
               LearnerLookahead(predict, predict_agent, states_of, proposal, value_fn, k, 1,
                                params.image_size, params.action_repeat))
    run = planning.run_closed_loop(planner, step_fn, np.stack(frames, 1), steps,
                                   jax.random.key(seed + 7), context_actions=np.stack(known, 1),
                                   execute=chunk, context=c)
    final = np.asarray(coverage[-1], np.float64)
    base = final if base is None else base
    rows[k] = {"final_coverage": policy_eval.policy_value(final).to_dict(),
               "gain_over_k1": policy_eval.policy_value(final - base).to_dict(),
               "per_episode": final.tolist()}
    if predict is not None:
      imagined = np.mean([p.scores[np.arange(episodes), p.index] for p in run["plans"]], axis=0)
      rows[k]["imagined_value"] = policy_eval.policy_value(imagined).to_dict()
    print(f"K={k}: coverage {final.mean():.3f}, gain {np.mean(final - base):+.3f} +- "
          f"{np.std(final - base, ddof=1) / np.sqrt(episodes):.3f}", flush=True)
  return rows


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--data", help="the Push-T builder directory (…/1.0.0); not with "
                      "--simulator")
  parser.add_argument("--config", default="configs/pusht.py:latent",
                      help="the profile whose data --data is (start states, protocol)")
  parser.add_argument("--candidates", default="1,10,50")
  parser.add_argument("--episodes", type=int, default=40)
  parser.add_argument("--steps", type=int, default=3000, help="MLP training steps")
  parser.add_argument("--batch", type=int, default=16, help="MLP batch (16: the world model's)")
  parser.add_argument("--perceived", action="store_true",
                      help="the learner reads the state off the frames, not the simulator's")
  parser.add_argument("--simulator", action="store_true",
                      help="plan with the simulator itself as the model instead (the reference)")
  parser.add_argument("--seed", type=int, default=0, help="the MLPs' seed")
  parser.add_argument("--out", required=True)
  args = parser.parse_args(argv)
  if not args.simulator and not args.data:
    parser.error("--data is needed to train the learner (or --simulator)")
  config = load_config(args.config)
  candidates = [int(k) for k in args.candidates.split(",")]
  if args.simulator:
    rows = plan(None, None, config, candidates, args.episodes, 0, False)
    with open(args.out, "w") as f:
      json.dump({"config": args.config, "model": "simulator", "candidates": rows}, f, indent=1)
    return 0
  split = read_split(args.data, "train", frames=args.perceived)
  split = split if args.perceived else split + (split[0],)  # (states, actions, seen states)
  keep = len(split[0]) - len(split[0]) // 10
  train, validation = (transitions(*(v[:keep] for v in split)),
                       transitions(*(v[keep:] for v in split)))
  predict, rate, _ = fit_selected(train, validation, args.steps, args.batch, args.seed)
  agent_train = dict(train, targets=agent_targets(split[0][:keep], split[2][:keep]))
  agent_validation = dict(validation, targets=agent_targets(split[0][keep:], split[2][keep:]))
  predict_agent, agent_rate, _ = fit_selected(agent_train, agent_validation, args.steps,
                                              args.batch, args.seed)
  rows = plan(predict, predict_agent, config, candidates, args.episodes, 0, args.perceived)
  with open(args.out, "w") as f:
    json.dump({"data": args.data, "config": args.config, "perceived": args.perceived,
               "mlp_seed": args.seed, "steps": args.steps, "batch": args.batch,
               "learning_rate": rate, "agent_learning_rate": agent_rate, "candidates": rows}, f,
              indent=1)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
