"""Improving a policy inside a world model, checked in the true environment.

--task reach (:mod:`wmjax.tasks.gridworld.reach`, the default): bring the green square onto the
red one within 8 steps; the return is minus the final distance in pixels, read from frames.
--task push (:mod:`wmjax.tasks.pusht.control`, a Push-T world model): push the T onto its goal;
the return is the goal's coverage in the last frame, checked in gym-pusht. A policy is
behaviour-cloned from the world model's training data, then improved for --rounds rounds of
filtered behaviour cloning on its own noisy episodes, twice with the same settings: in the world
model, and (the upper bound; --no-upper_bound leaves it out) in the true environment. After every
round both are checked from held-out start states in the true environment (paired gain over the
cloned policy) and in the world model (the imagined value and its gap to the true one).
--no-world_model runs the true-environment procedure alone, checked in the true environment only:
a cheap way to tune the procedure's settings on a CPU when the world model needs an accelerator.

    wmjax train --config configs/gridworld.py --workdir workdirs/gridworld     # the quickstart
    python experiments/improve/run.py --workdir workdirs/gridworld
    python experiments/improve/run.py --task push --workdir W/model             # a Push-T model

Writes to --out (default experiments/improve/results), named by the task's world and --seed
(``gridworld_seed0``, ``pusht_seed0``; ``pusht_seed0_true_environment`` with --no-world_model):
``.json`` (both procedures' round records, the final gains, the world model's share of the
true-environment gain, minutes), ``.md`` (the tables) and ``_before_after.png`` (true-environment
episodes from held-out start states: per state a row of the cloned policy, then one of the
policy improved in the world model, or in the true environment with --no-world_model).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time

import jax
import numpy as np

from wmjax import registry
from wmjax.eval.video import frame_grid, write_png
from wmjax.model import load_model
from wmjax.policy import LearnedPolicy
from wmjax.train.improve import ImproveSettings, improve_on_task, report_table
from wmjax.train.policy import clone_policy


def parse_args(argv=None) -> argparse.Namespace:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--task", choices=sorted(WORLDS), default="reach",
                      help="the control task: reach (gridworld) or push (Push-T)")
  parser.add_argument("--workdir", default="workdirs/gridworld",
                      help="the world model of the task's world (default: the quickstart's)")
  parser.add_argument("--world_model", action=argparse.BooleanOptionalAction, default=True,
                      help="improve in the world model; --no-world_model runs the true-environment "
                           "procedure alone, without imagined checks (the world model's network "
                           "never runs: a model trained for a step gives the data and actions)")
  parser.add_argument("--upper_bound", action=argparse.BooleanOptionalAction, default=True,
                      help="also improve in the true environment (the upper bound)")
  parser.add_argument("--out", default="experiments/improve/results")
  parser.add_argument("--clone_steps", type=int, default=300)
  parser.add_argument("--rounds", type=int, default=3)
  parser.add_argument("--rollouts", type=int, default=1024)
  parser.add_argument("--group", type=int, default=1, help="episodes per start state")
  parser.add_argument("--keep", type=float, default=0.1)
  parser.add_argument("--weighting", choices=("filter", "rwr"), default="filter")
  parser.add_argument("--temperature", type=float, default=1.0)
  parser.add_argument("--fit_steps", type=int, default=150)
  parser.add_argument("--evaluation_states", type=int, default=128)
  parser.add_argument("--evaluation_draw", type=int, default=1,
                      help="which draw of held-out start states checks the rounds (draw 0 chose "
                           "the settings; see RESULTS.md)")
  parser.add_argument("--pictures", type=int, default=6, help="start states in the PNG")
  parser.add_argument("--seed", type=int, default=0)
  return parser.parse_args(argv)


WORLDS = {"reach": "gridworld", "push": "pusht"}  # a task's world names its results


def final_gains(report: dict) -> dict:
  last = report["rounds"][-1]
  return {k: last[k] for k in ("true_value", "true_value_stderr", "true_gain", "true_gain_stderr",
                               "true_success", "imagined_value", "gap") if k in last}


def before_after(task, start: LearnedPolicy, improved: LearnedPolicy, count: int, draw: int
                 ) -> np.ndarray:
  """True-environment episodes of both policies from ``count`` held-out start states, one row
  each."""
  states = task.start_states(count, "evaluate", draw)
  key = jax.random.key(0)
  rows = [np.asarray(task.run(p.with_temperature(0.0), states, key)["frames"])
          for p in (start, improved)]
  return frame_grid([row[i] for i in range(count) for row in rows])


def main(argv=None) -> int:
  args = parse_args(argv)
  if not (args.world_model or args.upper_bound):
    raise SystemExit("nothing to run: --no-world_model with --no-upper_bound")
  logging.basicConfig(format="%(asctime)s %(message)s")
  logging.getLogger("wmjax").setLevel(logging.INFO)  # among others, a line per round
  began = time.time()
  model = load_model(args.workdir)
  task = registry.control_task(args.task, model.config)
  start, losses = clone_policy(model, task.controls, steps=args.clone_steps, seed=args.seed,
                               keep=task.demonstration)
  cloned = time.time()
  settings = ImproveSettings(rounds=args.rounds, rollouts=args.rollouts, group=args.group,
                             keep=args.keep, weighting=args.weighting,
                             temperature=args.temperature, fit_steps=args.fit_steps,
                             seed=args.seed)
  minutes, reports, policies = {"clone": (cloned - began) / 60}, {}, {}
  procedures = ((("world_model", False),) if args.world_model else ()) + (
      (("true_environment", True),) if args.upper_bound else ())
  for name, in_true in procedures:
    t = time.time()
    policies[name], reports[name] = improve_on_task(
        model, start, task, settings, evaluation_states=args.evaluation_states,
        evaluation_draw=args.evaluation_draw, in_true_environment=in_true,
        imagine=args.world_model)
    minutes[name] = (time.time() - t) / 60
  final = {name: final_gains(report) for name, report in reports.items()}
  result = {
      "command": "python experiments/improve/run.py " + " ".join(sys.argv[1:] if argv is None
                                                                  else argv),
      "world_model": {"workdir": args.workdir, "step": model.step},
      "clone": {"steps": args.clone_steps, "loss_first": float(losses[:10].mean()),
                "loss_last": float(losses[-10:].mean())},
      "settings": dataclasses.asdict(settings), "task": task.describe(),
      "world_model_procedure": reports.get("world_model"),
      "true_environment_procedure": reports.get("true_environment"),
      "final": final,
      "share_of_true_environment_gain": (final["world_model"]["true_gain"]
                                         / final["true_environment"]["true_gain"]
                                         if len(reports) == 2 else None),
      "minutes": minutes}
  os.makedirs(args.out, exist_ok=True)
  stem = os.path.join(args.out, f"{WORLDS[args.task]}_seed{args.seed}"
                      + ("" if args.world_model else "_true_environment"))
  with open(stem + ".json", "w") as f:
    json.dump(result, f, indent=2)
  tables = [f"## {name.replace('_', ' ')}\n\n{report_table(report)}"
            for name, report in reports.items()]
  summary = (f"The world model's improvement reaches "
             f"{result['share_of_true_environment_gain']:.0%} of the true environment's gain."
             if len(reports) == 2 else f"The {'true-environment' if args.world_model else 'world-model'}"
             " procedure was left out.")
  with open(stem + ".md", "w") as f:
    f.write("\n\n".join(tables + [summary]) + "\n")
  write_png(stem + "_before_after.png",
            before_after(task, start, policies[procedures[0][0]], args.pictures,
                         args.evaluation_draw))
  print("\n\n".join(tables + [summary]))
  print(f"wrote {stem}.json, .md and _before_after.png ({sum(minutes.values()):.1f} minutes)")
  return 0


if __name__ == "__main__":
  sys.exit(main())
