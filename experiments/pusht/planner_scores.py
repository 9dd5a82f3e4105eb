"""Push-T: how much of a world-model planner's choice is sampling noise, and how much model error?

At decision points of held-out planning episodes (the ``plan`` stream's start states, after 0, 2
and 4 actions of the proposal policy run in the simulator), ``K`` candidate chunks of the proposal
are imagined ``S`` times each with different rollout keys and scored by the planner's value
(coverage on the last imagined frame), and run once in the simulator from the same pose for
their true value (``SimulatorLookahead``, what a perfect model would score). From those:

* ``reliability``: the correlation, over candidates of one decision, between two imagined samples
  of the same candidates; 1 when the score is free of sampling noise;
* ``validity``: the correlation, over candidates, between the imagined score (one sample, or the
  mean of ``S``) and the true value;
* ``gain``: the true value of the candidate each rule picks minus the mean over the candidates
  (what ``K = 1`` gets on average), for the oracle (the true values), one imagined sample, the
  mean of ``S`` samples, and the mean less one standard deviation of the samples (pessimism);
* ``overvalued``: the chosen candidate's imagined score minus its true value, for the sample it
  was chosen on and for a fresh sample of it: when the fresh sample overvalues it as much, the
  planner's selection effect is the model's error on that candidate, not sampling noise.

Each figure is given for the planner's value and for the T's share of it (``block``: the goal's
pixels that show the block, without the agent's, which ``coverage`` counts too), to tell which of
the two the model's errors are in.

Standard errors are over episodes (each episode's decisions averaged first).

    python experiments/pusht/planner_scores.py --workdir W/model --step 1500 --out P.json

With ``--combine A.json B.json`` it measures nothing and asks of two such files, from two models
scored on the same candidates (the same ``--seed``, ``--episodes`` and ``--candidates``), whether
the two models' errors are independent enough for an ensemble to choose better
(``analyse_ensemble``): the correlation of the two models' errors over candidates, and the gain of
the sum of one sample of each against the mean of two samples of one model (the same number of
imagined rollouts).

    python experiments/pusht/planner_scores.py --combine A.json B.json --out E.json
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

POSITIONS = (0, 2, 4)


def _centered(x: np.ndarray) -> np.ndarray:
  """``x [D, K, ...]`` less each decision's mean over candidates."""
  return x - x.mean(1, keepdims=True)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
  return float(np.corrcoef(_centered(a).ravel(), _centered(b).ravel())[0, 1])


def _mean_se(values: np.ndarray, episodes: np.ndarray) -> dict:
  groups = np.asarray([values[episodes == e].mean() for e in np.unique(episodes)])
  return {"mean": float(groups.mean()), "stderr": float(groups.std(ddof=1) / np.sqrt(len(groups)))}


def analyse(imagined: np.ndarray, true: np.ndarray, episodes: np.ndarray) -> dict:
  """``imagined [D, K, S]`` scores and ``true [D, K]`` values of ``D`` decisions of ``episodes
  [D]`` -> the figures of the module's docstring."""
  d, _, s = imagined.shape
  rows = np.arange(d)

  def gain(score):
    return true[rows, score.argmax(1)] - true.mean(1)

  mean = imagined.mean(-1)
  rules = {"oracle": gain(true), "one_sample": np.mean([gain(imagined[..., i]) for i in range(s)], 0),
           "mean_of_samples": gain(mean),
           "mean_less_sd": gain(mean - imagined.std(-1, ddof=1))}
  chosen = imagined[..., 0].argmax(1)
  return {
      "decisions": d, "candidates": imagined.shape[1], "samples": s,
      "spread_over_candidates": {"true": float(_centered(true).std()),
                                 "imagined": float(_centered(imagined[..., 0]).std()),
                                 "sampling_sd": float(imagined.std(-1, ddof=1).mean())},
      "reliability": float(np.mean([_correlation(imagined[..., i], imagined[..., j])
                                    for i in range(s) for j in range(i + 1, s)])),
      "validity": {"one_sample": float(np.mean([_correlation(imagined[..., i], true)
                                                for i in range(s)])),
                   "mean_of_samples": _correlation(mean, true)},
      "gain": {name: _mean_se(v, episodes) for name, v in rules.items()},
      "mean_of_samples_minus_one_sample": _mean_se(rules["mean_of_samples"] - rules["one_sample"],
                                                   episodes),
      "overvalued": {
          "chosen_sample": _mean_se(imagined[rows, chosen, 0] - true[rows, chosen], episodes),
          "fresh_sample": _mean_se(imagined[rows, chosen, 1:].mean(-1) - true[rows, chosen],
                                   episodes)}}


def analyse_ensemble(first: np.ndarray, second: np.ndarray, true: np.ndarray,
                     episodes: np.ndarray) -> dict:
  """Two models' ``imagined [D, K, S]`` scores of the same candidates, ``true [D, K]`` and
  ``episodes [D]`` -> their errors' correlation and what choosing by their sum gains.

  ``slope``: for each model, the least-squares slope of its imagined score (the mean of its
  samples) on the true value over candidates, each decision's mean removed: 1 when the model's
  scores follow the true values, lower where its errors point away from them (with
  ``spread_over_candidates`` telling an error of direction from a model that moves too little).

  ``error_correlation``: over candidates (each decision's mean removed), between the two models'
  errors (the mean of their samples less the true value); near 1 when both models get the same
  candidates wrong, so that an ensemble of them cannot correct its members. Gains as in
  ``analyse``, averaged over every pairing of the samples: ``one_sample`` (either model),
  ``two_samples_one_model`` (the mean of two samples of one model), ``ensemble`` (one sample of
  each, summed), ``ensemble_min`` (their minimum, a pessimistic ensemble), and ``ensemble`` paired
  against ``two_samples_one_model``.
  """
  if first.shape != second.shape or first.shape[:2] != true.shape:
    raise ValueError(f"two models' scores must share one shape [D, K, S] with true [D, K]; got "
                     f"{first.shape}, {second.shape} and {true.shape}")
  s = first.shape[-1]
  rows = np.arange(len(true))

  def gain(score):
    return true[rows, score.argmax(1)] - true.mean(1)

  def pairs_of(model):
    return [model[..., [i, j]].mean(-1) for i in range(s) for j in range(i + 1, s)]

  one = np.mean([gain(m[..., i]) for m in (first, second) for i in range(s)], 0)
  two = np.mean([gain(p) for m in (first, second) for p in pairs_of(m)], 0)
  both = [(first[..., i], second[..., j]) for i in range(s) for j in range(s)]
  ensemble = np.mean([gain(a + b) for a, b in both], 0)
  errors = [_centered(m.mean(-1) - true).ravel() for m in (first, second)]
  truth = _centered(true).ravel()
  imagined = [_centered(m.mean(-1)).ravel() for m in (first, second)]
  return {
      "error_correlation": float(np.corrcoef(*errors)[0, 1]),
      "spread_over_candidates": {"true": float(truth.std()),
                                 "imagined": [float(m.std()) for m in imagined]},
      "slope": [float(m @ truth / (truth @ truth)) for m in imagined],
      "validity": {"one_sample": float(np.mean([_correlation(m[..., i], true)
                                                for m in (first, second) for i in range(s)])),
                   "two_samples_one_model": float(np.mean([_correlation(p, true)
                                                           for m in (first, second)
                                                           for p in pairs_of(m)])),
                   "ensemble": float(np.mean([_correlation(a + b, true) for a, b in both]))},
      "gain": {"oracle": _mean_se(gain(true), episodes), "one_sample": _mean_se(one, episodes),
               "two_samples_one_model": _mean_se(two, episodes),
               "ensemble": _mean_se(ensemble, episodes),
               "ensemble_min": _mean_se(np.mean([gain(np.minimum(a, b)) for a, b in both], 0),
                                        episodes)},
      "ensemble_minus_two_samples_one_model": _mean_se(ensemble - two, episodes)}


def combine(first: dict, second: dict) -> dict:
  """Two ``measure`` results of the same candidates -> ``analyse_ensemble`` for each score."""
  if first["true"] != second["true"] or first["episode"] != second["episode"]:
    raise ValueError("the two files score different candidates (their true values or episodes "
                     "differ): measure both with the same --seed, --episodes and --candidates")
  return {"workdirs": [first["workdir"], second["workdir"]],
          "steps": [first["step"], second["step"]], "seed": first["seed"],
          "held_out": bool(first["held_out"] and second["held_out"]),
          "analysis": {name: analyse_ensemble(np.asarray(first["imagined"])[i],
                                              np.asarray(second["imagined"])[i],
                                              np.asarray(first["true"])[i],
                                              np.asarray(first["episode"]))
                       for i, name in enumerate(("value", "block"))}}


def measure(workdir: str, step: int | None, episodes: int, candidates: int, samples: int,
            proposal_spec: str, seed: int) -> dict:
  """Imagined and true scores of every decision point (see the module's docstring)."""
  from wmjax.eval import planning
  from wmjax.eval.rewards import reward_from_spec
  from wmjax.frames import to_model
  from wmjax.model import load_model
  from wmjax.tasks.pusht import simulator as pusht
  from wmjax.tasks.pusht.dataset import INSTRUCTION, PushTConfig
  from wmjax.tasks.pusht.evaluate import (SimulatorLookahead, held_out, initial_states,
                                          policy_chunk, proposal_from_spec)

  model = load_model(workdir, step=step)
  config = model.config
  c, h = config.rollout.context, config.rollout.horizon
  value = reward_from_spec("coverage")
  proposal = proposal_from_spec(proposal_spec, policy_chunk(config))
  states = initial_states(config, episodes, "plan", seed)
  sim = pusht.PushTSimulator(episodes, model.image_shape[0],
                             PushTConfig.from_dict(config.data.pusht).action_repeat)
  frames, actions, _ = sim.start(states, c)
  planner = planning.Planner(model.world_model, model.params, proposal, value, candidates, h,
                             action_stats=model.action_stats,
                             normalization=config.data.normalization, codec=model.codec,
                             instruction=INSTRUCTION)
  lookahead = SimulatorLookahead(sim, proposal, value, candidates, h)
  key = jax.random.key(seed)

  goal = pusht.goal_mask(model.image_shape[0])

  def scores(videos):  # [B, K, T, H, W, 3] -> [2 (value, block), B, K]
    b, k = videos.shape[:2]
    last = videos.reshape((b * k,) + videos.shape[2:])
    block = np.asarray(pusht.object_masks(to_model(last[:, -1]))[0]) & goal
    return np.stack([np.asarray(value(last, INSTRUCTION)), block.sum((1, 2)) / goal.sum()]
                    ).reshape(2, b, k)

  imagined, true = [], []
  for position in range(max(POSITIONS) + 1):
    window = np.stack(frames[-c:], 1)
    known = np.stack(actions[-(c - 1):], 1) if c > 1 else None
    if position in POSITIONS:
      chunk = np.asarray(proposal(to_model(window), jax.random.fold_in(key, position), candidates))
      imagined.append(np.stack([scores(planner.imagine(
          window, known, chunk, jax.random.fold_in(key, 1000 * (position + 1) + i)))
          for i in range(samples)], -1))  # [2, B, K, S]
      true.append(scores(lookahead.imagine(window, known, chunk, None)))
      print(f"decisions after {position} actions scored", flush=True)
    step_key = jax.random.fold_in(key, 500 + position)
    action = np.asarray(proposal(to_model(window), step_key, 1))[:, 0, 0]
    frame, _ = sim.step(action)
    frames.append(frame)
    actions.append(action)
  return {"workdir": workdir, "step": step, "proposal": proposal_spec, "seed": seed,
          "positions": list(POSITIONS), "held_out": held_out(config, states),
          "imagined": np.concatenate(imagined, 1).tolist(),  # [2 (value, block), D, K, S]
          "true": np.concatenate(true, 1).tolist(),  # [2, D, K]
          "episode": np.tile(np.arange(episodes), len(POSITIONS)).tolist()}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--workdir", help="the model's workdir (checkpoints/)")
  parser.add_argument("--combine", nargs=2, metavar="JSON",
                      help="two files this script wrote, of two models on the same candidates: "
                           "analyse them as an ensemble instead of measuring")
  parser.add_argument("--step", type=int, default=None, help="checkpoint step (default: last)")
  parser.add_argument("--episodes", type=int, default=20)
  parser.add_argument("--candidates", type=int, default=10)
  parser.add_argument("--samples", type=int, default=3)
  parser.add_argument("--proposal", default="push:0.2")
  parser.add_argument("--seed", type=int, default=0, help="the plan stream's draw and the keys")
  parser.add_argument("--out", required=True, help="JSON file for every number")
  args = parser.parse_args(argv)
  if (args.workdir is None) == (args.combine is None):
    parser.error("give either --workdir (measure) or --combine A.json B.json (analyse)")
  if args.combine:
    runs = []
    for path in args.combine:
      with open(path) as f:
        runs.append(json.load(f))
    result = combine(*runs)
    with open(args.out, "w") as f:
      json.dump(result, f, indent=1)
    print(json.dumps(result["analysis"], indent=1))
    return 0
  if args.samples < 2 or args.candidates < 2:
    parser.error("need --samples >= 2 and --candidates >= 2")
  result = measure(args.workdir, args.step, args.episodes, args.candidates, args.samples,
                   args.proposal, args.seed)
  result["analysis"] = {
      name: analyse(np.asarray(result["imagined"])[i], np.asarray(result["true"])[i],
                    np.asarray(result["episode"])) for i, name in enumerate(("value", "block"))}
  with open(args.out, "w") as f:
    json.dump(result, f)
  print(json.dumps(result["analysis"], indent=1))
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
