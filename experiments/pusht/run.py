"""Push-T: does a world model rank policies like the simulator, and does planning in it help?

One script for the whole experiment, in stages that each resume where an earlier run stopped
(see RESULTS.md beside it for measured runs):

1. ``data``: simulate Push-T episodes with a scripted pusher at noise levels 0 / 0.1 / 0.2 / 0.5
   (``wmjax data prepare pusht``; host CPUs only, ``--data_workers`` processes at once);
2. ``classifier``: a success classifier (coverage >= --success_coverage) on the dataset's frames
   (host CPUs only);
3. ``codec``: for a profile that diffuses in the latents of a codec fitted to the data (``latent``):
   the codec (``wmjax data train-codec``, :data:`CODEC`) in WORKDIR/codec and the dataset encoded
   with it (``wmjax data encode``) in WORKDIR/latents; nothing for pixel profiles;
4. ``train``: the world model (``wmjax train --config configs/pusht.py:PROFILE``; resumes from
   its last checkpoint);
5. ``policy``: five policies (the pusher at four noise levels and a do-nothing policy) in
   gym-pusht and closed loop in the world model from the same initial states, scored by the
   coverage read from the imagined frames and by the classifier (``wmjax eval-policy``);
6. ``plan``: model-predictive control ranking K candidate chunks from the noisy pusher, executed
   in gym-pusht, one K at a time (``wmjax plan``);
7. ``summary``: WORKDIR/summary.json (``held_out``: every start state checked against the
   training split's; ``pearson`` / ``spearman`` with bootstrap ``*_ci95``, ``ranking_matches``;
   ``block_iou_push_end``, the T's IoU at the end of the ``push`` rollouts; per K the final
   coverage with its paired gain over K = 1 and the chosen plans' imagined value beside their
   value in the simulator, the exploitability gap and its selection effect over K = 1;
   ``minutes`` of wall time summed over the stages and their resumes, from WORKDIR/timing.json;
   ``codec_held_out``, a fitted codec's reconstruction metrics on held-out frames)
   and the tables. Policy evaluation and planning start from held-out states (their own random
   streams, :func:`wmjax.data.synthetic.stream`).

    python experiments/pusht/run.py --workdir workdirs/pusht                 # CPU, <= 90 minutes
    python experiments/pusht/run.py --workdir /tmp/pusht --smoke             # plumbing, minutes
    python experiments/pusht/run.py --profile latent --workdir workdirs/pusht-latent
    JAX_PLATFORMS=cpu python experiments/pusht/run.py --profile h100 \\
        --workdir workdirs/pusht-h100 --stage data --stage classifier          # on the host
    python experiments/pusht/run.py --profile h100 --workdir workdirs/pusht-h100 --minutes 9
    experiments/pusht/h100_device.sh workdirs/pusht-h100 5     # or: on a machine without an index

The GPU machine needs no package index: ``device_wheels.sh`` downloads the wheels it lacks and
``h100_device.sh`` installs them there, trains and runs the policy evaluation in one command.

``--config.KEY=VALUE`` overrides change the profile's config (after ``--smoke``'s), e.g.
``--config.train.num_steps=10000``; give the same ones to every command of a run (a changed
config is refused by the resumed training).

``--minutes M`` stops after about M minutes, for jobs with a time limit: training is asked to
save and stop (as on SIGTERM), and no new stage or K starts after the deadline; the script then
exits 3, and the same command continues. Finished stages are skipped: the dataset and the
classifier are kept, training resumes from its checkpoint, ``policy_eval/policy_eval.json`` and
each ``plan/K<k>/plan.json`` mark their work done.

Outputs land in WORKDIR: data/, classifier/, codec/ and latents/ (``latent``), model/,
policy_eval/ (with videos/: per policy an mp4 or GIF and a PNG frame grid, simulator beside world
model), plan/, summary.json, results.json (all raw results) and timing.json.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import time

STAGES = ("data", "classifier", "codec", "train", "policy", "plan", "summary")
HOST_STAGES = {"data", "classifier", "summary"}  # never need an accelerator
PROFILES = ("cpu", "latent", "h100")
# the codec a latent profile's run fits to its data (wmjax.train.codec.CodecRecipe fields; the
# one screened in RESULTS.md; its latent channels are the config's frame_shape[-1]), and the
# smoke run's
CODEC = dict(widths=(16, 32, 64), steps=1500)
SMOKE_CODEC = dict(steps=10, batch_size=8, train_frames=128, eval_frames=8)
CONFIG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "configs", "pusht.py")
SMOKE = ["data.pusht.train_episodes=16", "data.pusht.test_episodes=4", "model.depth=2",
         "model.hidden_size=32", "model.num_heads=2", "model.dtype='float32'",
         "model.attention_impl='xla'", "batch_size=8", "train.num_steps=20",
         "optim.total_steps=20", "optim.warmup_steps=5", "train.checkpoint_every=20",
         "train.eval_every=20", "train.eval_windows=4", "data.num_workers=0"]
UNFINISHED = 3  # exit code: stopped at the deadline, run the same command again
# episode lengths in control steps of 0.1 s (policy evaluation, planning): the same time whatever
# the data's action_repeat
CONTROL_STEPS, PLAN_CONTROL_STEPS = 32, 24


def _usable_cpus() -> int:
  """The CPUs this process may run on (all of the machine's where the system does not say)."""
  return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


class Deadline:
  """``minutes`` from now (or never)."""

  def __init__(self, minutes: float | None):
    self.end = None if minutes is None else time.monotonic() + 60 * minutes

  def passed(self) -> bool:
    return self.end is not None and time.monotonic() >= self.end

  @contextlib.contextmanager
  def terminating(self):
    """Within this block, ask this process to stop by SIGTERM once the deadline has come (the
    training loop saves a checkpoint and stops), again every 10 s until the block ends: a
    SIGTERM that comes before the loop listens (while it compiles) is ignored."""
    if self.end is None:  # no deadline: SIGTERM keeps its usual meaning
      yield
      return
    done = threading.Event()

    def send():
      if not done.wait(max(0.0, self.end - time.monotonic())):
        while not done.is_set():
          os.kill(os.getpid(), signal.SIGTERM)
          done.wait(10.0)

    previous = signal.signal(signal.SIGTERM, lambda *_: None)
    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    try:
      yield
    finally:
      done.set()
      thread.join()
      signal.signal(signal.SIGTERM, previous)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--profile", choices=PROFILES, default="cpu",
                      help="configs/pusht.py profile (default cpu)")
  parser.add_argument("--stage", action="append", choices=STAGES,
                      help="run only these stages, repeatable (default: all, in order)")
  parser.add_argument("--minutes", type=float, default=None,
                      help="stop after about this many minutes; rerun to continue")
  parser.add_argument("--episodes", type=int, default=48, help="episodes per policy")
  parser.add_argument("--steps", type=int, default=None,
                      help="actions per episode, each held for data.pusht.action_repeat control "
                           "steps of 0.1 s (default: 32 control steps' worth)")
  parser.add_argument("--plan_episodes", type=int, default=20, help="seeds for planning")
  parser.add_argument("--plan_steps", type=int, default=None,
                      help="actions per planning episode (default: 24 control steps' worth)")
  parser.add_argument("--candidates", default="1,5,10,50", help="K values, with 1")
  parser.add_argument("--plan_sampling_steps", type=int, default=None,
                      help="sampler steps when imagining planning candidates (default: the "
                           "config's sampling.num_steps)")
  parser.add_argument("--lookahead", action=argparse.BooleanOptionalAction, default=True,
                      help="also plan with the simulator as the model (a reference that does "
                           "not depend on the world model; default on)")
  parser.add_argument("--video_format", choices=("mp4", "gif"), default="mp4",
                      help="closed-loop videos: mp4 (needs imageio-ffmpeg) or gif")
  parser.add_argument("--success_coverage", type=float, default=0.5,
                      help="classifier label: coverage >= this")
  parser.add_argument("--data_workers", type=int, default=_usable_cpus(),
                      help="processes simulating the dataset at once (default: the CPUs this "
                           "process may use; the data is the same for any number)")
  parser.add_argument("--smoke", action="store_true",
                      help="tiny data, model and episodes: checks the plumbing in minutes")
  args, extra = parser.parse_known_args(argv)
  stages = [s for s in STAGES if s in (args.stage or STAGES)]
  if set(stages) <= HOST_STAGES:  # before JAX is imported: keep an accelerator free
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
  from wmjax.config import ConfigError, overrides_of
  try:
    args.overrides = overrides_of(extra)
    experiment = Experiment(args)
  except ConfigError as error:
    parser.error(str(error))
  return experiment.run(stages, Deadline(args.minutes))


class Experiment:
  """The stages of one Push-T run in one workdir."""

  def __init__(self, args):
    from wmjax.config import load_config

    self.args = args
    self.workdir = os.path.abspath(args.workdir)
    self.config_file = f"{os.path.normpath(CONFIG)}:{args.profile}"
    self.overrides = [f"data.data_dir={os.path.join(self.workdir, 'data')!r}"]
    self.candidates = [int(k) for k in args.candidates.split(",")]
    if args.smoke:
      self.overrides += SMOKE
    self.overrides += args.overrides  # the model's config: given to every stage that reads it
    if 1 not in self.candidates:
      raise SystemExit(f"--candidates must include 1 (the baseline of the gains), got "
                       f"{args.candidates}")
    self.config = load_config(self.config_file, self.overrides)
    # a latent profile without a codec named: the run fits one and encodes its data with it
    self.fits_codec = self.config.codec.kind == "vae" and not (
        self.config.codec.path or self.config.codec.random_vae)
    if self.fits_codec:
      self.overrides += [f"codec.path={self.path('codec')!r}",
                         f"data.latents_dir={self.path('latents')!r}"]
      self.config = load_config(self.config_file, self.overrides)
    from wmjax.tasks.pusht.evaluate import actions_for
    self.episodes, self.plan_episodes = args.episodes, args.plan_episodes
    self.steps = args.steps or actions_for(self.config, CONTROL_STEPS)
    self.plan_steps = args.plan_steps or actions_for(self.config, PLAN_CONTROL_STEPS)
    if args.smoke:
      self.episodes, self.steps, self.plan_episodes, self.plan_steps = 4, 8, 2, 4
      self.candidates = [1, 3]
    self.model_dir = os.path.join(self.workdir, "model")
    self.classifier_dir = os.path.join(self.workdir, "classifier")

  def path(self, *parts: str) -> str:
    return os.path.join(self.workdir, *parts)

  def run(self, stages: list[str], deadline: Deadline) -> int:
    for stage in stages:
      if deadline.passed() and stage != "summary":  # the summary takes milliseconds: a run whose
        # last long stage ended just past the deadline still writes it
        print(f"\nstopped at the deadline before stage {stage!r}; run the same command again to "
              f"continue", flush=True)
        return UNFINISHED
      print(f"\n## stage {stage}", flush=True)
      start = time.monotonic()
      finished = getattr(self, stage)(deadline) is not False
      self._add_time(stage, time.monotonic() - start)
      if not finished:
        print(f"\nstage {stage!r} stopped at the deadline; run the same command again to "
              f"continue", flush=True)
        return UNFINISHED
    return 0

  def _add_time(self, stage: str, seconds: float) -> None:
    """Add ``seconds`` to the stage's wall time in WORKDIR/timing.json (summed over resumes)."""
    os.makedirs(self.workdir, exist_ok=True)
    path = self.path("timing.json")
    timing = {}
    if os.path.exists(path):
      with open(path) as f:
        timing = json.load(f)
    timing[stage] = timing.get(stage, 0.0) + seconds
    with open(path, "w") as f:
      json.dump(timing, f, indent=2)

  def _minutes(self) -> dict:
    """Wall minutes per stage so far and in all (WORKDIR/timing.json): the stages before the
    summary, which is timed after it has written them."""
    with open(self.path("timing.json")) as f:
      timing = json.load(f)
    return {"minutes": round(sum(timing.values()) / 60, 2),
            "stage_minutes": {k: round(v / 60, 2) for k, v in timing.items()}}

  def wmjax(self, *command: str, overrides=()) -> int:
    from wmjax import cli
    argv = list(command) + [f"--config.{o}" for o in overrides]
    print("\n$ wmjax " + " ".join(argv), flush=True)
    return cli.main(argv)

  def _check(self, code: int, command: str) -> None:
    if code:
      raise SystemExit(f"wmjax {command} failed with exit code {code}")

  # ------------------------------------------------------------------ stages
  def data(self, deadline) -> None:
    from wmjax.tasks.pusht.dataset import PushTConfig, prepare
    print(prepare(self.config.data.data_dir, PushTConfig.from_dict(self.config.data.pusht),
                  workers=self.args.data_workers))

  def classifier(self, deadline) -> None:
    metrics_file = os.path.join(self.classifier_dir, "metrics.json")
    if os.path.exists(metrics_file):
      print(f"done before: {metrics_file}")
      return
    metrics = train_classifier(self.config, self.classifier_dir, self.args.success_coverage,
                               steps=50 if self.args.smoke else 1500)
    with open(metrics_file, "w") as f:
      json.dump(metrics, f, indent=2)

  def codec(self, deadline) -> None:
    if not self.fits_codec:
      given = self.config.codec.path or self.config.codec.random_vae
      print(f"nothing to fit: codec.kind={self.config.codec.kind!r}"
            + (f", given {given!r}" if given else ""))
      return
    from wmjax.train.codec import REPORT
    folder, latents = self.config.codec.path, self.config.data.latents_dir
    if os.path.exists(os.path.join(folder, REPORT)):  # the folder is written whole or not at all
      print(f"done before: {folder}")
    else:
      recipe = {**CODEC, "latent_channels": self.config.frame_shape[-1],
                **(SMOKE_CODEC if self.args.smoke else {})}
      flags = [f"--{k}={','.join(map(str, v)) if isinstance(v, tuple) else v}"
               for k, v in recipe.items()]
      self._check(self.wmjax("data", "train-codec", "--config", self.config_file, "--out", folder,
                             *flags, overrides=self.overrides), "data train-codec")
    if os.path.exists(latents):  # likewise
      print(f"done before: {latents}")
    else:
      self._check(self.wmjax("data", "encode", "--config", self.config_file, "--out", latents,
                             overrides=self.overrides), "data encode")

  def train(self, deadline) -> bool:
    if self._trained_steps() == self.config.train.num_steps:
      print(f"done before: {self.model_dir} holds step {self.config.train.num_steps}")
      return True
    with deadline.terminating():
      code = self.wmjax("train", "--config", self.config_file, "--workdir", self.model_dir,
                        overrides=self.overrides)
    if code in (128 + signal.SIGTERM, 128 + signal.SIGINT) and deadline.passed():
      return False
    self._check(code, "train")
    return True

  def policy(self, deadline) -> None:
    out = self.path("policy_eval")
    if os.path.exists(os.path.join(out, "policy_eval.json")):
      print(f"done before: {out}/policy_eval.json")
      return
    self._check(self.wmjax(
        "eval-policy", "--workdir", self.model_dir, "--episodes", str(self.episodes), "--steps",
        str(self.steps), "--reward", "coverage", "--reward", f"classifier:{self.classifier_dir}",
        "--scan", "--video_format", self.args.video_format, "--out", out), "eval-policy")

  def plan(self, deadline) -> bool:
    from wmjax.tasks.pusht.evaluate import planning_table
    rows, first = {}, None
    for k in self.candidates:
      out = self.path("plan", f"K{k}")
      if not os.path.exists(os.path.join(out, "plan.json")):
        if deadline.passed():
          return False
        self._check(self.wmjax(
            "plan", "--workdir", self.model_dir, "--episodes", str(self.plan_episodes),
            "--steps", str(self.plan_steps), "--candidates", str(k), "--out", out,
            *(["--lookahead"] if self.args.lookahead else []),
            overrides=([] if self.args.plan_sampling_steps is None else
                       [f"sampling.num_steps={self.args.plan_sampling_steps}"])), "plan")
      with open(os.path.join(out, "plan.json")) as f:
        result = json.load(f)
      rows.update(result["candidates"])
      first = first or result
    merged = {**first, "candidates": rows, "table": planning_table(rows)}
    with open(self.path("plan", "plan.json"), "w") as f:
      json.dump(merged, f, indent=2)
    with open(self.path("plan", "plan.md"), "w") as f:
      f.write(merged["table"] + "\n")
    return True

  def summary(self, deadline) -> None:
    from wmjax.tasks.pusht.evaluate import summarize
    from wmjax.train.codec import REPORT
    results = {}
    files = {"classifier": "classifier/metrics.json", "policy_eval": "policy_eval/policy_eval.json",
             "plan": "plan/plan.json", **({"codec": f"codec/{REPORT}"} if self.fits_codec else {})}
    missing = [f"{file} (stage {name.removesuffix('_eval')})" for name, file in files.items()
               if not os.path.exists(self.path(file))]
    if missing:
      raise SystemExit(f"the summary reads the results of the stages before it, and "
                       f"{self.workdir} lacks {', '.join(missing)}: run those stages first")
    for name, file in files.items():
      with open(self.path(file)) as f:
        results[name] = json.load(f)
    summary = {"profile": self.args.profile, "config": self.config.name,
               "train_steps": self._trained_steps(), **self._minutes(),
               **({"codec_held_out": results["codec"]["held_out"]} if self.fits_codec else {}),
               **summarize(results["policy_eval"], results["plan"], "coverage")}
    with open(self.path("results.json"), "w") as f:
      json.dump(results, f, indent=2)
    with open(self.path("summary.json"), "w") as f:
      json.dump(summary, f, indent=2)
    with open(self.path("policy_eval", "policy_eval.md")) as f:
      print("\n# Policy evaluation\n\n" + f.read())
    print(f"classifier: {json.dumps(results['classifier'])}")
    print("\n## Planning (final simulator coverage)\n")
    print(results["plan"]["table"])
    print(f"\nwrote {self.path('summary.json')}:\n{json.dumps(summary, indent=2)}")

  def _trained_steps(self) -> int | None:
    """The step a finished training ended at (its ``metrics.json``, written only at the end), or
    None before that."""
    metrics = os.path.join(self.model_dir, "metrics.json")
    if not os.path.exists(metrics):
      return None
    with open(metrics) as f:
      return json.load(f)["step"]


def train_classifier(config, out: str, success_coverage: float, *, steps: int) -> dict:
  """Fit the success classifier on the training split of ``config``'s dataset; test accuracy on
  the held-out split."""
  import numpy as np

  from wmjax.data.sources import dataset_dir
  from wmjax.eval import rewards

  builder_dir = dataset_dir(config.data)
  label = f"coverage >= {success_coverage}"
  frames, labels = rewards.labelled_frames(builder_dir, "train", "coverage", success_coverage,
                                           max_frames=4000)
  test_frames, test_labels = rewards.labelled_frames(builder_dir, "test", "coverage",
                                                     success_coverage)
  classifier, train_metrics = rewards.train_success_classifier(
      frames, labels, steps=steps, batch_size=64, label=label)
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
