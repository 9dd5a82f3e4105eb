"""MetaWorld: does a two-camera world model follow a robot arm and rank arm policies like the
simulator does?

One script for the whole experiment, in stages that each resume where an earlier run stopped
(RESULTS.md beside it has the measured runs):

1. ``data``: simulate MetaWorld episodes from two cameras (``wmjax data prepare metaworld``):
   the scripted expert at action noise 0 / 0.2 / 0.4 / 0.6, random and idle agents;
2. ``reader``: fit the frame reader (:mod:`wmjax.tasks.metaworld.reader`: end effector pixel,
   hand and object positions, success, per view) on the training split; its own error on the
   test split is WORKDIR/reader/metrics.json;
3. ``train``: the world model (``wmjax train --config configs/metaworld.py:PROFILE``);
4. ``metrics``: open loop on test episodes: the end effector's pixel error, the object's error and
   the views' hand gap per generated frame, beside copy-last (WORKDIR/metrics.json, PNG);
5. ``policy``: five policies (the expert at four noise levels, idle) from held-out start states
   in the simulator and closed loop in the world model (WORKDIR/policy_eval/);
6. ``summary``: WORKDIR/summary.json (``held_out``, ``pearson`` / ``spearman`` with bootstrap
   ``*_ci95``, the end effector's error after 8 imagined frames against copy-last, the reader's
   own error, ``minutes`` from WORKDIR/timing.json).

    python experiments/metaworld/run.py --profile cpu --workdir workdirs/metaworld
    python experiments/metaworld/run.py --profile tiled --workdir workdirs/metaworld-tiled
    python experiments/metaworld/run.py --workdir /tmp/mw --smoke          # plumbing, minutes

``--config.KEY=VALUE`` overrides change the profile's config (after ``--smoke``'s), e.g.
``--config.seed=1`` for a second training seed; give the same ones to every command of a run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

STAGES = ("data", "reader", "train", "metrics", "policy", "summary")
PROFILES = ("cpu", "tiled", "drawer", "h100")
CONFIG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "configs",
                      "metaworld.py")
SMOKE = ["data.metaworld.train_episodes=6", "data.metaworld.test_episodes=4",
         "data.metaworld.episode_length=8", "model.depth=2", "model.hidden_size=32",
         "model.num_heads=2", "batch_size=4", "train.num_steps=4", "optim.total_steps=4",
         "optim.warmup_steps=1", "train.checkpoint_every=4", "train.eval_every=4",
         "train.eval_windows=2", "sampling.num_steps=2"]
IMAGINED = 8  # the end effector's error is reported after this many imagined frames


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--profile", choices=PROFILES, default="cpu",
                      help="configs/metaworld.py profile (default cpu)")
  parser.add_argument("--stage", action="append", choices=STAGES,
                      help="run only these stages, repeatable (default: all, in order)")
  parser.add_argument("--episodes", type=int, default=24, help="episodes per policy")
  parser.add_argument("--metric_episodes", type=int, default=32,
                      help="test episodes of the open-loop arm metrics")
  parser.add_argument("--reader_steps", type=int, default=2000, help="reader training steps")
  parser.add_argument("--reader_blur", type=float, default=0.0,
                      help="train the reader on frames blended towards their blur by up to this "
                           "weight (wmjax.tasks.metaworld.reader.degrade)")
  parser.add_argument("--reader_noise", type=float, default=0.0,
                      help="and with Gaussian noise of up to this standard deviation")
  parser.add_argument("--reading_weight", type=float, default=None,
                      help="the policies track the hand: each new reading moves the position "
                           "predicted from their actions by this weight (1: the newest reading "
                           "alone; default wmjax.tasks.metaworld.evaluate.READING_WEIGHT)")
  parser.add_argument("--data_workers", type=int, default=max(1, len(os.sched_getaffinity(0))),
                      help="processes simulating the dataset at once (the data is the same for "
                           "any number)")
  parser.add_argument("--smoke", action="store_true",
                      help="tiny data, model and episodes: checks the plumbing in minutes")
  args, extra = parser.parse_known_args(argv)
  from wmjax.config import ConfigError, overrides_of
  try:
    args.overrides = overrides_of(extra)
    experiment = Experiment(args)
  except ConfigError as error:
    parser.error(str(error))
  for stage in [s for s in STAGES if s in (args.stage or STAGES)]:
    print(f"\n## stage {stage}", flush=True)
    start = time.monotonic()
    getattr(experiment, stage)()
    experiment.add_time(stage, time.monotonic() - start)
  return 0


class Experiment:
  """The stages of one MetaWorld run in one workdir."""

  def __init__(self, args):
    from wmjax.config import load_config

    self.args = args
    self.workdir = os.path.abspath(args.workdir)
    self.config_file = f"{os.path.normpath(CONFIG)}:{args.profile}"
    self.overrides = [f"data.data_dir={self.path('data')!r}"]
    if args.smoke:
      self.overrides += SMOKE
      args.episodes, args.metric_episodes, args.reader_steps = 3, 2, 20
    self.overrides += args.overrides
    self.config = load_config(self.config_file, self.overrides)
    self.model_dir, self.reader_dir = self.path("model"), self.path("reader")

  def path(self, *parts: str) -> str:
    return os.path.join(self.workdir, *parts)

  def add_time(self, stage: str, seconds: float) -> None:
    """Add ``seconds`` to the stage's wall time in WORKDIR/timing.json (summed over resumes)."""
    os.makedirs(self.workdir, exist_ok=True)
    timing = _read(self.path("timing.json")) or {}
    timing[stage] = timing.get(stage, 0.0) + seconds
    _write(self.path("timing.json"), timing)

  def _params(self):
    from wmjax.tasks.metaworld.dataset import MetaWorldConfig
    return MetaWorldConfig.from_dict(self.config.data.metaworld)

  def _builder_dir(self) -> str:
    from wmjax.tasks.metaworld.dataset import prepare
    return prepare(self.config.data.data_dir, self._params(), workers=self.args.data_workers)

  def _model(self):
    from wmjax.model import load_model
    return load_model(self.model_dir)

  def _reader(self):
    from wmjax.tasks.metaworld.reader import ArmReader
    return ArmReader.load(self.reader_dir)

  # ------------------------------------------------------------------ stages
  def data(self) -> None:
    print(self._builder_dir())

  def reader(self) -> None:
    metrics_file = os.path.join(self.reader_dir, "metrics.json")
    if os.path.exists(metrics_file):
      print(f"done before: {metrics_file}")
      return
    from wmjax.tasks.metaworld.reader import fit_reader, labelled_frames
    builder_dir = self._builder_dir()
    train = labelled_frames(builder_dir, "train", max_frames=20000)
    test = labelled_frames(builder_dir, "test")
    reader, metrics = fit_reader(*train, validation=test, steps=self.args.reader_steps,
                                 blur=self.args.reader_blur, noise=self.args.reader_noise)
    reader.save(self.reader_dir)
    _write(metrics_file, metrics)
    print(json.dumps(metrics["validation"], indent=2))

  def train(self) -> None:
    metrics = _read(os.path.join(self.model_dir, "metrics.json"))
    if metrics and metrics["step"] == self.config.train.num_steps:
      print(f"done before: {self.model_dir} holds step {metrics['step']}")
      return
    from wmjax import cli
    argv = ["train", "--config", self.config_file, "--workdir", self.model_dir] + [
        f"--config.{o}" for o in self.overrides]
    print("\n$ wmjax " + " ".join(argv), flush=True)
    if cli.main(argv):
      raise SystemExit("wmjax train failed")

  def metrics(self) -> None:
    out = self.path("metrics.json")
    if os.path.exists(out):
      print(f"done before: {out}")
      return
    import numpy as np

    from wmjax.data.rlds import decode_image
    from wmjax.data.sources import ArrayRecordEpisodes
    from wmjax.tasks.metaworld.evaluate import arm_metrics
    source = ArrayRecordEpisodes(self._builder_dir(), "test")
    count = min(self.args.metric_episodes, len(source))
    episodes = [source.episode(i) for i in range(count)]
    frames = np.stack([np.stack([decode_image(im, None) for im in e.images]) for e in episodes])
    model = self._model()
    actions = np.stack([e.actions[:-1] for e in episodes])
    ee_px = np.stack([e.extras["ee_px"] for e in episodes])
    state = np.stack([e.extras["state"] for e in episodes])
    context = model.config.rollout.context
    length = min(frames.shape[1], context + IMAGINED)
    result = arm_metrics(model, self._reader(), frames[:, :length], actions[:, :length - 1],
                         ee_px[:, :length], state[:, :length],
                         out_png=self.path("results", "open_loop.png"))
    result["episodes"] = count
    _write(out, result)
    print(json.dumps({k: v["ee_px_error"] for k, v in result.items() if isinstance(v, dict)}))

  def policy(self) -> None:
    out = self.path("policy_eval")
    if os.path.exists(os.path.join(out, "policy_eval.json")):
      print(f"done before: {out}/policy_eval.json")
      return
    from wmjax.tasks.metaworld.evaluate import (READING_WEIGHT, evaluate_policies,
                                                training_hand_motion)
    weight = READING_WEIGHT if self.args.reading_weight is None else self.args.reading_weight
    model = self._model()
    motion = training_hand_motion(model.config) if weight < 1 else None
    results = evaluate_policies(model, self._reader(), out, episodes=self.args.episodes,
                                motion=motion, reading_weight=weight)
    for name, value in results["policies"].items():
      print(f"{name:12s} simulator {value['simulator']['mean']:.3f}  world model "
            f"{value['world_model']['mean']:.3f}")
    print(json.dumps(results["agreement"]))

  def summary(self) -> None:
    policy = _read(self.path("policy_eval", "policy_eval.json"))
    metrics = _read(self.path("metrics.json"))
    reader = _read(os.path.join(self.reader_dir, "metrics.json"))
    timing = _read(self.path("timing.json")) or {}
    summary = {"task": self._params().task, "profile": self.args.profile,
               "views": list(self._params().views), "model_views": self.config.model.views,
               "seed": self.config.seed, "train_steps": self.config.train.num_steps}
    if policy:
      summary.update(
          held_out=policy["held_out"], episodes=policy["episodes"],
          reading_weight=policy.get("reading_weight", 1.0),
          pearson=policy["agreement"]["pearson"], spearman=policy["agreement"]["spearman"],
          pearson_ci95=policy["intervals"]["pearson"],
          spearman_ci95=policy["intervals"]["spearman"],
          values={name: {"simulator": v["simulator"]["mean"],
                         "world_model": v["world_model"]["mean"]}
                  for name, v in policy["policies"].items()})
    if metrics:
      last = {name: {key: metrics[name][key][-1] for key in
                     ("ee_px_error", "ee_px_error_stderr", "object_error_cm",
                      "view_hand_gap_cm")} for name in ("model", "copy_last", "truth")}
      summary["after_imagined_frames"] = len(metrics["model"]["ee_px_error"])
      summary["arm_metrics_last_frame"] = last
    if reader:
      summary["reader_test_error"] = reader["validation"]
    summary["minutes"] = round(sum(timing.values()) / 60, 2)
    summary["stage_minutes"] = {k: round(v / 60, 2) for k, v in timing.items()}
    _write(self.path("summary.json"), summary)
    print(json.dumps(summary, indent=2))


def _read(path: str):
  if not os.path.exists(path):
    return None
  with open(path) as f:
    return json.load(f)


def _write(path: str, value) -> None:
  from wmjax.eval.report import to_json_safe
  os.makedirs(os.path.dirname(path), exist_ok=True)
  with open(path, "w") as f:
    json.dump(to_json_safe(value), f, indent=2)


if __name__ == "__main__":
  sys.exit(main())
