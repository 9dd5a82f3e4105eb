"""Improve a policy inside a gridworld world model, then check it in the true gridworld.

A policy is cloned from the model's random-action data, improved for a few rounds on its own
noisy episodes imagined by the model (the ``reach`` task: bring the green square onto the red
one), and both are run in the true gridworld from the same held-out start states.

  python examples/improve_policy.py workdirs/gridworld --rounds 3
"""

import argparse

import jax
import numpy as np

from wmjax import registry
from wmjax.model import load_model
from wmjax.train.improve import ImproveSettings, improve, world_model_rollout
from wmjax.train.policy import clone_policy


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir")
  parser.add_argument("--rounds", type=int, default=3)
  parser.add_argument("--rollouts", type=int, default=1024)
  parser.add_argument("--clone_steps", type=int, default=300)
  parser.add_argument("--fit_steps", type=int, default=150)
  args = parser.parse_args(argv)

  model = load_model(args.workdir)                        # imports its task, the gridworld
  task = registry.control_task("reach", model.config)
  policy, _ = clone_policy(model, task.controls,          # the green square's velocity only
                           steps=args.clone_steps,         # behaviour cloning
                           keep=task.demonstration)    # all the random-action data

  held_out = task.start_states(64, "evaluate")
  imagined = world_model_rollout(model, task, task.start_states(args.rollouts, "plan",
                                                               exclude=held_out))
  settings = ImproveSettings(rounds=args.rounds, rollouts=args.rollouts,
                             fit_steps=args.fit_steps)
  improved, history = improve(policy, imagined, task.reward, settings)

  key = jax.random.key(1)
  before = task.reward(task.run(policy, held_out, key)["frames"])       # in the true gridworld
  after = task.reward(task.run(improved, held_out, key)["frames"])
  gain = after - before
  print(f"true return {before.mean():.2f} -> {after.mean():.2f} px "
        f"(paired gain {gain.mean():+.2f} ± {gain.std(ddof=1) / np.sqrt(len(gain)):.2f})")
  for record in history[1:]:
    print(f"round {record['round']}: imagined exploration return "
          f"{record['explore_return']:.2f}, {record['kept_episodes']} episodes kept")
  return {"before": before, "after": after, "history": history}
