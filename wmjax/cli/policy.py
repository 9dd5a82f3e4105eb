"""Learnable policies on a world model's control task: ``wmjax clone-policy`` (behaviour cloning
from the model's dataset) and ``wmjax improve`` (rounds of filtered behaviour cloning on the
policy's own imagined episodes, checked in the task's true environment); the work is
:mod:`wmjax.train.policy`'s and :mod:`wmjax.train.improve`'s."""

from __future__ import annotations

import json
import os

from wmjax.cli import common


TASK_HELP = "control task: reach (gridworld, the default) or push (Push-T)"


def _model_and_task(args):
  from wmjax import registry
  from wmjax.model import load_model
  model = load_model(args.workdir, step=args.step, params=args.params)
  return model, registry.control_task(args.task, model.config)


def clone_policy(args, extra) -> int:
  """Behaviour-clone a policy from the training split of a world model's dataset (read and
  normalised as the model reads it) and write it to --out (orbax parameters beside
  policy.json). The policy sets only the action dimensions --task controls, and learns from the
  episodes --task names as demonstrations (reach: all; push: the noisy scripted pushes)."""
  del extra
  from wmjax.train.policy import clone_policy as clone
  model, task = _model_and_task(args)
  policy, losses = clone(model, task.controls, steps=args.steps, chunk=args.chunk,
                         batch_size=args.batch_size, learning_rate=args.learning_rate,
                         seed=args.seed, keep=task.demonstration)
  policy.save(args.out, info={"trained_by": "behaviour cloning", "workdir": args.workdir,
                              "task": args.task, "steps": args.steps,
                              "final_loss": float(losses[-10:].mean())})
  print(f"behaviour cloning: loss {losses[:10].mean():.3f} -> {losses[-10:].mean():.3f} over "
        f"{args.steps} steps; wrote {args.out}")
  return 0


def improve(args, extra) -> int:
  """Improve a policy on a control task inside the world model (or, with --true_environment,
  in the task's true environment: the upper bound): --rounds rounds of --rollouts noisy
  episodes (--group of them from each start state), the best --keep fraction (of each group)
  kept and cloned. After every round the deterministic policy
  is checked from --evaluation_states held-out start states in the true environment and in the
  world model. Writes the policy to --out and report.json / report.md beside it."""
  del extra
  from wmjax.policy import load_policy
  from wmjax.train.improve import ImproveSettings, improve_on_task, report_table
  model, task = _model_and_task(args)
  settings = ImproveSettings(rounds=args.rounds, rollouts=args.rollouts, group=args.group,
                             keep=args.keep, weighting=args.weighting, temperature=args.temperature,
                             fit_steps=args.fit_steps, seed=args.seed)
  if os.path.exists(args.out):
    raise FileExistsError(f"{args.out} exists; wmjax improve writes a new policy directory")
  policy, report = improve_on_task(model, load_policy(args.policy), task, settings,
                                   evaluation_states=args.evaluation_states,
                                   in_true_environment=args.true_environment)
  policy.save(args.out, info={"trained_by": f"improvement in the {report['improved_in']}",
                              "from": args.policy, "workdir": args.workdir, "task": args.task})
  with open(os.path.join(args.out, "report.json"), "w") as f:
    json.dump(report, f, indent=2)
  table = report_table(report)
  with open(os.path.join(args.out, "report.md"), "w") as f:
    f.write(table + "\n")
  print(table)
  print(f"wrote {args.out} (policy, report.json, report.md)")
  return 0


def add_parser(sub) -> None:
  """The ``clone-policy`` and ``improve`` commands."""
  clone = sub.add_parser("clone-policy", help="behaviour-clone a policy from a world model's data",
                         description=clone_policy.__doc__)
  clone.add_argument("--workdir", required=True, help=common.WORKDIR_HELP)
  clone.add_argument("--out", required=True, help="new directory for the policy")
  clone.add_argument("--task", default="reach", help=TASK_HELP)
  clone.add_argument("--chunk", type=int, default=1, help="actions per policy call (default 1)")
  clone.add_argument("--steps", type=int, default=300, help="training steps (default 300)")
  clone.add_argument("--batch_size", type=int, default=64)
  clone.add_argument("--learning_rate", type=float, default=1e-3)
  clone.add_argument("--seed", type=int, default=0)
  common.checkpoint_args(clone, dtype=False)
  common.register(clone, clone_policy)

  better = sub.add_parser("improve", help="improve a policy in the world model, checked in the "
                                          "task's true environment", description=improve.__doc__)
  better.add_argument("--workdir", required=True, help=common.WORKDIR_HELP)
  better.add_argument("--policy", required=True, help="policy directory (wmjax clone-policy)")
  better.add_argument("--out", required=True, help="new directory for the improved policy")
  better.add_argument("--task", default="reach", help=TASK_HELP)
  better.add_argument("--rounds", type=int, default=3)
  better.add_argument("--rollouts", type=int, default=1024, help="episodes per round")
  better.add_argument("--group", type=int, default=1,
                      help="episodes per start state, each weighed against its state's (default 1: "
                           "one each, all weighed together)")
  better.add_argument("--keep", type=float, default=0.1,
                      help="fraction of episodes kept (of each group's, with --group)")
  better.add_argument("--weighting", choices=("filter", "rwr"), default="filter",
                      help="filter: keep the best --keep; rwr: reward-weighted regression")
  better.add_argument("--temperature", type=float, default=1.0, help="exploration noise")
  better.add_argument("--fit_steps", type=int, default=150, help="training steps per round")
  better.add_argument("--evaluation_states", type=int, default=128,
                      help="held-out start states of the check after every round")
  better.add_argument("--true_environment", action="store_true",
                      help="improve in the true environment instead (the upper bound)")
  better.add_argument("--seed", type=int, default=0)
  common.checkpoint_args(better, dtype=False)
  common.register(better, improve)
