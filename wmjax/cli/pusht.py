"""The simulator tasks' commands: ``wmjax eval-policy`` (policy values in the world model vs the
simulator, for a Push-T or a MetaWorld model) and ``wmjax plan`` (model-predictive control run in
the gym-pusht simulator, Push-T only); the work is :mod:`wmjax.tasks.pusht.evaluate`'s and
:mod:`wmjax.tasks.metaworld.evaluate`'s."""

from __future__ import annotations

from wmjax.cli import common

# episode length when --steps is not given, in control steps of 0.1 s: the same time whatever the
# dataset's action_repeat
DEFAULT_CONTROL_STEPS = 24
METAWORLD = "wmjax.tasks.metaworld"
OVERRIDES_NOTE = ("Inference settings of the checkpoint's config can be overridden, "
                  "e.g. --config.sampling.num_steps=4.")


def _steps(args, model) -> int:
  """``--steps``, or the actions of :data:`DEFAULT_CONTROL_STEPS` control steps."""
  from wmjax.tasks.pusht.evaluate import actions_for
  return args.steps or actions_for(model.config, DEFAULT_CONTROL_STEPS)


def eval_policy(args, extra) -> int:
  """Evaluate policies in a Push-T world model and, for ground truth, in the gym-pusht simulator
  from the same initial states: Monte Carlo values (mean ± stderr), Pearson / Spearman / Kendall,
  rank agreement, MMRV, value gap; writes policy_eval.json, policy_eval.md and one video per
  policy (simulator | world model | difference)."""
  model = common.inference_model(args.workdir, args, extra)
  if model.config.get("task") == METAWORLD:
    return _eval_arm_policy(args, model)
  if args.reader or args.reading_weight is not None:
    raise ValueError("--reader and --reading_weight are for a MetaWorld model; this one's task is "
                     f"{model.config.get('task')!r}")
  from wmjax.eval.rewards import reward_from_spec
  from wmjax.tasks.pusht.evaluate import (evaluate_policies, policies_from_specs, policy_chunk,
                                          policy_report)
  policies = policies_from_specs(args.policy, policy_chunk(model.config))
  rewards = {spec: reward_from_spec(spec) for spec in args.reward or ["coverage"]}
  out = args.out or f"{args.workdir}/policy_eval"
  result = evaluate_policies(model, policies, rewards, episodes=args.episodes,
                             steps=_steps(args, model),
                             seed=args.seed, scan=args.scan, out=out, videos=args.videos,
                             video_format=args.video_format)
  print(policy_report(result))
  print(f"wrote {out}/policy_eval.json, policy_eval.md and videos/")
  return 0


def _eval_arm_policy(args, model) -> int:
  """MetaWorld: image-based policies (the expert on the state a reader reads off frames) in the
  simulator and closed loop in the world model, from held-out start states."""
  from wmjax.tasks.metaworld.evaluate import (DEFAULT_POLICIES, READING_WEIGHT,
                                              evaluate_policies, training_hand_motion)
  from wmjax.tasks.metaworld.reader import ArmReader
  if not args.reader:
    raise ValueError("a MetaWorld model's policies act on, and are scored by, a frame reader: "
                     "give --reader DIR (experiments/metaworld/run.py --stage reader fits one)")
  if args.reward or args.scan:
    raise ValueError("--reward and --scan are Push-T's; a MetaWorld model is scored by its "
                     "--reader's success")
  weight = READING_WEIGHT if args.reading_weight is None else args.reading_weight
  if not 0.0 < weight <= 1.0:
    raise ValueError(f"--reading_weight must be in (0, 1], got {weight}")
  reader = ArmReader.load(args.reader)
  motion = training_hand_motion(model.config) if weight < 1 else None
  out = args.out or f"{args.workdir}/policy_eval"
  result = evaluate_policies(model, reader, out, specs=args.policy or DEFAULT_POLICIES,
                             episodes=args.episodes, steps=args.steps, seed=args.seed,
                             motion=motion, reading_weight=weight)
  for name, value in result["policies"].items():
    print(f"{name:12s} simulator {value['simulator']['mean']:.3f} ± "
          f"{value['simulator']['stderr']:.3f}   world model {value['world_model']['mean']:.3f} ± "
          f"{value['world_model']['stderr']:.3f}")
  print(f"pearson {result['agreement']['pearson']:.3f} {result['intervals']['pearson']}, "
        f"spearman {result['agreement']['spearman']:.3f}; held out: {result['held_out']}")
  print(f"wrote {out}/policy_eval.json and one PNG per policy")
  return 0


def plan(args, extra) -> int:
  """Model-predictive control by ranking with a Push-T world model, executed in the gym-pusht
  simulator: at each replanning, K chunks from the proposal policy are imagined in one batch,
  scored by the value function, and the best one's first actions are executed; final simulator
  coverage for each K."""
  from wmjax.eval.rewards import reward_from_spec
  from wmjax.tasks.pusht.evaluate import plan_in_simulator, policy_chunk, proposal_from_spec
  model = common.inference_model(args.workdir, args, extra)
  length = args.plan_length or policy_chunk(model.config)
  proposal = proposal_from_spec(args.proposal, length)
  out = args.out or f"{args.workdir}/plan"
  candidates = [int(k) for k in args.candidates.split(",")]
  result = plan_in_simulator(model, proposal, reward_from_spec(args.value), candidates,
                             episodes=args.episodes, steps=_steps(args, model), seed=args.seed,
                             execute=args.execute or length, lookahead=args.lookahead, out=out)
  print(result["table"])
  print(f"wrote {out}/plan.json and plan.md")
  return 0


def _simulator_args(parser, default_out: str) -> None:
  parser.add_argument("--workdir", required=True,
                      help="workdir of a model trained on Push-T (or, for eval-policy, "
                           "MetaWorld), with checkpoints/")
  parser.add_argument("--episodes", type=int, default=32,
                      help="episodes, i.e. initial states (default 32)")
  parser.add_argument("--steps", type=int, default=None,
                      help=f"actions per episode, each held for the dataset's "
                           f"data.pusht.action_repeat control steps of 0.1 s (default: "
                           f"{DEFAULT_CONTROL_STEPS} control steps' worth)")
  parser.add_argument("--seed", type=int, default=0)
  common.checkpoint_args(parser, dtype=False)
  parser.add_argument("--out", default=None, help=f"output directory (WORKDIR/{default_out})")


def add_parser(sub) -> None:
  """The ``eval-policy`` and ``plan`` commands."""
  policy = sub.add_parser("eval-policy", help="Push-T or MetaWorld: policy values in the world "
                                              "model vs the simulator",
                          description=eval_policy.__doc__, epilog=OVERRIDES_NOTE)
  _simulator_args(policy, "policy_eval")
  policy.add_argument("--policy", action="append",
                      help="Push-T: push | push:NOISE | stay | learned:DIR (wmjax clone-policy "
                           "/ improve) | module:attribute (default: push, push:0.1, push:0.2, "
                           "push:0.5, stay); MetaWorld: expert | expert:NOISE | random | idle "
                           "(default: expert, expert:0.2, expert:0.3, expert:0.4, idle); "
                           "repeatable")
  policy.add_argument("--reader", default=None,
                      help="MetaWorld: the frame reader's directory (its policies act on the "
                           "state it reads, and it reads success off imagined frames)")
  policy.add_argument("--reading_weight", type=float, default=None,
                      help="MetaWorld: the policies track the hand, each new reading moving the "
                           "position predicted from their actions by this weight, in (0, 1] (1: "
                           "the newest reading alone; default wmjax.tasks.metaworld.evaluate."
                           "READING_WEIGHT; the motion is fitted on the model's training data)")
  policy.add_argument("--reward", action="append",
                      help="Push-T: coverage | vlm | classifier:DIR | goal:IMAGE, repeatable, all "
                           "scored on the same rollouts (default: coverage)")
  policy.add_argument("--scan", action="store_true",
                      help="roll out inside one jitted scan (pure-JAX policies)")
  policy.add_argument("--videos", type=int, default=4, help="episodes per policy video")
  policy.add_argument("--video_format", choices=("mp4", "gif"), default="mp4",
                      help="mp4 (needs imageio-ffmpeg) or gif (default mp4)")
  common.register(policy, eval_policy, takes_overrides=True)

  planner = sub.add_parser("plan", help="Push-T: model-predictive control by ranking, run in the "
                                        "gym-pusht simulator",
                           description=plan.__doc__, epilog=OVERRIDES_NOTE)
  _simulator_args(planner, "plan")
  planner.add_argument("--candidates", default="1,5,10,50",
                       help="comma-separated K values (default 1,5,10,50)")
  planner.add_argument("--proposal", default="push:0.2",
                       help="proposal policy: push:NOISE | stay | module:attribute (default "
                            "push:0.2)")
  planner.add_argument("--plan_length", type=int, default=None,
                       help="actions per candidate (default: the policy chunk the data was "
                            "collected with, data.pusht.chunk)")
  planner.add_argument("--execute", type=int, default=None,
                       help="actions executed before replanning (default: the whole candidate)")
  planner.add_argument("--value", default="coverage",
                       help="value function on imagined frames: coverage | vlm | classifier:DIR | "
                            "goal:IMAGE (default coverage)")
  planner.add_argument("--lookahead", action="store_true",
                       help="also plan with the simulator itself as the model (a reference)")
  common.register(planner, plan, takes_overrides=True)
