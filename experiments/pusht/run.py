"""Push-T: does a world model rank policies like the simulator, and does planning in it help?

One script for the whole experiment (see RESULTS.md beside it for a measured run):

1. simulate Push-T episodes with a scripted pusher at noise levels 0 / 0.1 / 0.2 / 0.5 and train
   a world model on them (``wmjax train --config configs/pusht.py``; resumes if interrupted);
2. train a success classifier (coverage >= --success_coverage) on the dataset's frames;
3. evaluate five policies (the pusher at four noise levels and a do-nothing policy) in gym-pusht
   and closed loop in the world model from the same initial states, with two rewards on the
   imagined frames (coverage read from the frame, and the classifier), and print the agreement;
4. plan by ranking K in {1, 5, 10, 50} candidate chunks from the noisy pusher, executed in
   gym-pusht, and print the final coverage per K.

    python experiments/pusht/run.py --workdir workdirs/pusht          # the measured run
    python experiments/pusht/run.py --workdir /tmp/pusht --smoke      # minutes: plumbing only

Outputs land in WORKDIR (model/, policy_eval/, plan/, classifier/, results.json).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from wmjax import cli


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--data_dir", default=None, help="TFDS data directory (WORKDIR/data)")
  parser.add_argument("--episodes", type=int, default=48, help="episodes per policy")
  parser.add_argument("--steps", type=int, default=32, help="control steps per episode")
  parser.add_argument("--plan_episodes", type=int, default=20, help="seeds for planning")
  parser.add_argument("--plan_steps", type=int, default=24)
  parser.add_argument("--candidates", default="1,5,10,50")
  parser.add_argument("--plan_sampling_steps", type=int, default=4,
                      help="DDIM steps when imagining planning candidates")
  parser.add_argument("--success_coverage", type=float, default=0.5,
                      help="classifier label: coverage >= this")
  parser.add_argument("--smoke", action="store_true",
                      help="tiny data, model and episodes: checks the plumbing in minutes")
  args = parser.parse_args(argv)
  workdir = os.path.abspath(args.workdir)
  data_dir = os.path.abspath(args.data_dir or os.path.join(workdir, "data"))
  overrides = [f"--config.data.data_dir='{data_dir}'"]
  episodes, steps, plan_episodes, plan_steps = (args.episodes, args.steps, args.plan_episodes,
                                                args.plan_steps)
  candidates = args.candidates
  if args.smoke:
    overrides += ["--config.data.pusht.train_episodes=16", "--config.data.pusht.test_episodes=4",
                  "--config.model.depth=2", "--config.model.hidden_size=32",
                  "--config.train.num_steps=20", "--config.optim.total_steps=20",
                  "--config.optim.warmup_steps=5",
                  "--config.train.checkpoint_every=20", "--config.train.eval_every=20",
                  "--config.train.eval_windows=4"]
    episodes, steps, plan_episodes, plan_steps, candidates = 4, 8, 2, 8, "1,3"
  model_dir = os.path.join(workdir, "model")

  def run(*command):
    print("\n$ wmjax " + " ".join(command), flush=True)
    code = cli.main(list(command))
    if code:
      raise SystemExit(f"wmjax {command[0]} failed with exit code {code}")

  run("train", "--config", "configs/pusht.py", "--workdir", model_dir, *overrides)
  classifier_dir = os.path.join(workdir, "classifier")
  classifier_metrics = train_classifier(model_dir, classifier_dir, args.success_coverage,
                                        smoke=args.smoke)
  common = ["--workdir", model_dir, "--episodes", str(episodes), "--steps", str(steps)]
  run("eval-policy", *common, "--reward", "coverage", "--reward",
      f"classifier:{classifier_dir}", "--scan", "--out", os.path.join(workdir, "policy_eval"))
  run("plan", "--workdir", model_dir, "--episodes", str(plan_episodes), "--steps",
      str(plan_steps), "--candidates", candidates, "--lookahead", "--out",
      os.path.join(workdir, "plan"),
      f"--config.sampling.num_steps={args.plan_sampling_steps}")

  results = {"classifier": classifier_metrics}
  for name, file in (("policy_eval", "policy_eval/policy_eval.json"), ("plan", "plan/plan.json")):
    with open(os.path.join(workdir, file)) as f:
      results[name] = json.load(f)
  with open(os.path.join(workdir, "results.json"), "w") as f:
    json.dump(results, f, indent=2)
  with open(os.path.join(workdir, "policy_eval", "policy_eval.md")) as f:
    print("\n# Policy evaluation\n\n" + f.read())
  print(f"classifier: {json.dumps(classifier_metrics)}")
  print("\n## Planning (final simulator coverage)\n")
  print(results["plan"]["table"])
  return 0


def train_classifier(model_dir: str, out: str, success_coverage: float, *, smoke: bool) -> dict:
  """Fit the success classifier on the world model's training split; test accuracy on the
  held-out split."""
  import numpy as np

  from wmjax.data.sources import dataset_dir
  from wmjax.eval import rewards
  from wmjax.model import load_model

  config = load_model(model_dir).config
  builder_dir = dataset_dir(config.data)
  label = f"coverage >= {success_coverage}"
  frames, labels = rewards.labelled_frames(builder_dir, "train", "coverage", success_coverage,
                                           max_frames=4000)
  test_frames, test_labels = rewards.labelled_frames(builder_dir, "test", "coverage",
                                                     success_coverage)
  classifier, train_metrics = rewards.train_success_classifier(
      frames, labels, steps=50 if smoke else 1500, batch_size=64, label=label)
  classifier.save(out)
  predicted = classifier.probabilities(test_frames) > 0.5
  metrics = {"label": label, "train_frames": int(len(frames)),
             "train_positive_fraction": float(labels.mean()),
             "test_frames": int(len(test_frames)),
             "test_accuracy": float((predicted == test_labels).mean()),
             "test_balanced_accuracy": float(np.mean([(predicted[test_labels == v] == v).mean()
                                                      for v in (True, False)
                                                      if (test_labels == v).any()])),
             **{f"final_train_{k}": v for k, v in train_metrics.items()}}
  print(f"classifier ({label}): {metrics}", flush=True)
  return metrics


if __name__ == "__main__":
  sys.exit(main())
