"""Writes the results page, docs/results.md, and its plots from the committed results JSON.

    python docs/make_results.py [--out DIR]    # DIR/results.md, DIR/assets/results/*.png

Every figure on the page is read from the JSON file its section names (or, for IRASim's PyTorch
anchors, from the constants below, which quote benchmarks/RESULTS.md); the dates, commits and
machines are those the RESULTS files give for each run. tests/test_results_page.py regenerates
the page and fails when it differs from the committed one: edit this script, not the page.
"""

import argparse
import json
import pathlib
import re

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend is chosen first)

ROOT = pathlib.Path(__file__).resolve().parents[1]
PUSHT = ROOT / "experiments" / "pusht" / "results"
IMPROVE = ROOT / "experiments" / "improve" / "results"
METAWORLD = ROOT / "experiments" / "metaworld" / "results" / "cpu_seed0_tracked"
BENCH = ROOT / "benchmarks" / "results"
ASSETS = pathlib.Path("assets") / "results"

# IRASim's own PyTorch code on one H100 (benchmarks/RESULTS.md, "Accelerator: one H100 80GB
# HBM3"): training at B=8, bf16 autocast + SDPA; rollouts of batch 8 with torch.compile.
IRASIM_TRAIN_MFU_PERCENT = 25
IRASIM_TRAIN_SAMPLES_PER_S = 17.5
IRASIM_ROLLOUT_FRAMES_PER_S = {59: 20.4, 10: 120.5}  # model calls per block -> frames/s
TEST_BUDGET_S = 480  # the suite's 8-minute budget (benchmarks/RESULTS.md, "Test command")

# (JSON under benchmarks/results, label): the train steps of the RESULTS tables
TRAIN_SETTINGS = [
  ("h100/xl-b16-dots-xla.json", "H100 XL/2 dots, XLA attention"),
  ("h100/xl-b16-dots-auto-tx.json", "H100 XL/2 dots, auto attention"),
  ("h100/xl-b16-dots-auto-unrolled.json", "H100 XL/2 dots, unrolled"),
  ("h100/xl-b16-full-auto.json", "H100 XL/2 full remat"),
  ("h100/wpe-b16-dots-auto-tx.json", "H100 WPE-600M dots"),
  ("h100/wpe-b16-full-auto.json", "H100 WPE-600M full remat"),
  ("h200/settings-train-xl-dots-False-gpu.json", "H200 XL/2 dots, unrolled"),
  ("h200/settings-train-xl-dots_attention-False-gpu.json", "H200 XL/2 dots_attention"),
  ("h200/settings-train-xl-none-False-2-gpu.json", "H200 XL/2 no remat, 2 micro-batches"),
]
ROLLOUTS = [
  ("h100/xl-roll-59.json", "XL/2, 59 calls, batch 8"),
  ("h100/xl-roll-10.json", "XL/2, 10 calls, batch 8"),
  ("h100/xl-roll-10-b32.json", "XL/2, 10 calls, batch 32"),
  ("h100/wpe-roll-59-kv.json", "WPE-600M, 59 calls, KV cache"),
  ("h100/wpe-roll-10-kv.json", "WPE-600M, 10 calls, KV cache"),
  ("h100/wpe-roll-10-nokv.json", "WPE-600M, 10 calls, no cache"),
]


def _load(path: pathlib.Path):
  """A JSON file's contents."""
  return json.loads(path.read_text())


def _rel(*paths: pathlib.Path) -> str:
  """The paths relative to the repository, in backticks, comma-separated."""
  return ", ".join(f"`{p.relative_to(ROOT)}`" for p in paths)


def _pm(mean: float, stderr: float, sign: str = "") -> str:
  """``mean ± stderr`` to 3 decimals (``sign="+"`` writes the mean's sign)."""
  return f"{mean:{sign}.3f} ± {stderr:.3f}"


def _ci(pair) -> str:
  """An interval to 3 decimals."""
  return f"[{pair[0]:.3f}, {pair[1]:.3f}]"


def _figure(ncols: int = 1):
  """A 6 x 3.5 inch figure of ``ncols`` panels side by side."""
  return plt.subplots(1, ncols, figsize=(6, 3.5), dpi=100)


def _save(fig, path: pathlib.Path) -> pathlib.Path:
  """Saves without the matplotlib version in the metadata, so the file depends on the data."""
  fig.tight_layout()
  fig.savefig(path, dpi=100, metadata={"Software": None})
  plt.close(fig)
  return path


def _curve(folder: pathlib.Path, summary: pathlib.Path) -> tuple[list, dict]:
  """(step, Pearson, its 95 % interval, T IoU at the end of `push`) per checkpoint of a run:
  the curve's policy evaluations, then the run's own summary at its last step."""
  points = []
  for path in folder.glob("*.json"):
    run = _load(path)
    agreement = run["rewards"]["coverage"]
    points.append((int(re.search(r"step(\d+)", path.name).group(1)),
                   agreement["agreement"]["pearson"], agreement["agreement_ci95"]["pearson"],
                   run["policies"]["push"]["block"]["world_model"]["end"]["block_iou"]))
  last = _load(summary)
  points.append((last["train_steps"], last["pearson"], last["pearson_ci95"],
                 last["block_iou_push_end"]))
  return sorted(points), last


def pusht_curve(out: pathlib.Path) -> tuple[str, pathlib.Path]:
  """Push-T: policy-ranking Pearson and the pushed T's IoU over training, two runs."""
  xeon = PUSHT / "latent_selfforced_xeon_2026-11-29"
  runs = [("self-forced latent (the profile)", xeon / "curve", xeon / "summary.json"),
          ("plain latent", PUSHT / "curve_3000steps_2026-11-28",
           PUSHT / "latent_3000steps_2026-11-28" / "summary.json")]
  fig, (left, right) = _figure(2)
  finals = []
  for (label, folder, summary), colour in zip(runs, ("C0", "C1")):
    points, last = _curve(folder, summary)
    steps, pearson, ci, iou = zip(*points)
    errors = [[p - c[0] for p, c in zip(pearson, ci)], [c[1] - p for p, c in zip(pearson, ci)]]
    left.errorbar(steps, pearson, yerr=errors, marker="o", capsize=3, color=colour, label=label)
    right.plot(steps, iou, marker="o", color=colour)
    finals.append((last, points[-1]))
  right.axhline(finals[0][0]["block_iou_push_end_copy_first_frame"], color="gray", ls="--",
                label="copying the first frame")
  left.set(title="Policy ranking", xlabel="training step", ylabel="Pearson r, 95 % interval")
  right.set(title="T IoU at the end of push", xlabel="training step", ylabel="IoU (fraction)")
  left.legend(fontsize=7, loc="lower right")
  right.legend(fontsize=7, loc="lower right")
  fig.suptitle("Push-T, held-out start states, over training", fontsize=10)
  image = _save(fig, out / "pusht_training_curve.png")
  (sf, (_, sf_r, sf_ci, sf_iou)), (plain, (_, pl_r, pl_ci, pl_iou)) = finals
  caption = (
    f"The self-forced `latent` profile (fresh clone of 5f33c2b, 2-core Intel Xeon VM, 2026-11-29) "
    f"ends its {sf['train_steps']} steps ({sf['stage_minutes']['train']} training minutes) at "
    f"Pearson {sf_r:.3f} {_ci(sf_ci)} and a pushed-T IoU of {sf_iou:.3f}; the plain profile "
    f"(2ed1df1, AMD EPYC with AVX-512, 2026-11-28, {plain['stage_minutes']['train']} minutes) at "
    f"{pl_r:.3f} {_ci(pl_ci)} and {pl_iou:.3f}.\nCopying the first frame keeps "
    f"{sf['block_iou_push_end_copy_first_frame']:.3f}. Minutes are not recorded per checkpoint, "
    "so the x axis is training steps.")
  files = _rel(*(p for _, f, s in runs for p in (f, s)))
  return _section("Push-T over training", caption, image, files, ["experiments/pusht/RESULTS.md"])


def policy_values(out: pathlib.Path) -> tuple[str, pathlib.Path]:
  """World-model against simulator policy values, Push-T and MetaWorld, with standard errors."""
  pusht, metaworld = _load(PUSHT / "summary.json"), _load(METAWORLD / "policy_eval.json")
  panels = [("Push-T: coverage", {name: (p["simulator"], p["simulator_stderr"], p["world_model"],
                                         p["world_model_stderr"])
                                  for name, p in pusht["policies"].items()}),
            ("MetaWorld: success rate", {
              name: (p["simulator"]["mean"], p["simulator"]["stderr"], p["world_model"]["mean"],
                     p["world_model"]["stderr"]) for name, p in metaworld["policies"].items()})]
  fig, axes = _figure(2)
  for ax, (title, values) in zip(axes, panels):
    top = max(max(v[0] + v[1], v[2] + v[3]) for v in values.values()) * 1.1
    ax.plot([0, top], [0, top], color="gray", ls="--", label="y = x")
    for name, (sim, sim_se, wm, wm_se) in values.items():
      ax.errorbar(sim, wm, xerr=sim_se, yerr=wm_se, fmt="o", capsize=2, ms=4, label=name)
    ax.set(title=title, xlabel="simulator value (fraction)", ylabel="world-model value (fraction)",
           xlim=(-0.02, top), ylim=(-0.02, top))  # below 0 so that a point at 0 shows
    ax.legend(fontsize=6, loc="best")
  fig.suptitle("Policy values, mean ± standard error", fontsize=10)
  image = _save(fig, out / "policy_values.png")
  expert = {side: _pm(v["mean"], v["stderr"]) for side, v in metaworld["policies"]["expert"].items()
            if side in ("simulator", "world_model")}
  caption = (
    f"Push-T, the self-forced `latent` profile in one piece (53c275a, AMD EPYC without AVX-512, "
    f"2026-11-29, {pusht['episodes']['policy_eval']} held-out episodes a policy): Pearson "
    f"{pusht['pearson']:.3f} {_ci(pusht['pearson_ci95'])}, Spearman {pusht['spearman']:.3f}.\n"
    f"MetaWorld `button-press-v3`, `cpu` profile, policies tracking the hand (bc9475b, AMD EPYC, "
    f"2026-12-07, {metaworld['episodes']} held-out episodes a policy): Pearson {metaworld['agreement']['pearson']:.3f} "
    f"{_ci(metaworld['intervals']['pearson'])}, Spearman {metaworld['agreement']['spearman']:.3f}; "
    f"the world model sees `expert` succeed {expert['world_model']} of the time where the "
    f"simulator sees {expert['simulator']}.")
  files = _rel(PUSHT / "summary.json", METAWORLD / "policy_eval.json")
  return _section("Policy values: world model against simulator", caption, image, files,
                  ["experiments/pusht/RESULTS.md", "experiments/metaworld/RESULTS.md"])


def _rounds(path: pathlib.Path, procedure: str) -> list[dict]:
  """The rounds of an improvement result's ``world_model`` or ``true_environment`` procedure."""
  return _load(path)[f"{procedure}_procedure"]["rounds"]


def improvement(out: pathlib.Path) -> tuple[str, pathlib.Path]:
  """Policy improvement rounds: the true gain of a policy improved in the world model and in
  the true environment, gridworld and Push-T, two seeds each."""
  grid = [IMPROVE / f"gridworld_seed{s}.json" for s in (0, 1)]
  model = [IMPROVE / "pusht_cpu_profile" / f"pusht_seed{s}.json" for s in (0, 1)]
  true = [IMPROVE / f"pusht_seed{s}_true_environment_group8_t05_256states.json" for s in (0, 1)]
  panels = [  # (title, y label, [(seed, improved in the world model?, rounds)])
    ("Gridworld reach", "paired true gain (px)",
     [(s, wm, _rounds(p, "world_model" if wm else "true_environment"))
      for s, p in enumerate(grid) for wm in (True, False)]),
    ("Push-T push (256 states)", "paired true gain (coverage)",
     [(s, True, _rounds(p, "world_model")) for s, p in enumerate(model)]
     + [(s, False, _rounds(p, "true_environment")) for s, p in enumerate(true)])]
  fig, axes = _figure(2)
  for ax, (title, ylabel, series) in zip(axes, panels):
    for seed, in_model, rounds in series:
      ax.errorbar([r["round"] for r in rounds], [r["true_gain"] for r in rounds],
                  yerr=[r["true_gain_stderr"] for r in rounds], marker="o", capsize=2,
                  ls="-" if in_model else "--", color=f"C{seed}",
                  label=f"seed {seed}, " + ("world model" if in_model else "true env."))
    ax.set(title=title, xlabel="improvement round", ylabel=ylabel, xticks=[0, 1, 2, 3])
  axes[0].legend(fontsize=6, loc="lower right")  # the same colours and lines in both panels
  fig.suptitle("Policy improvement: improved in the world model (solid) or the true env. (dashed)",
               fontsize=9)
  image = _save(fig, out / "policy_improvement.png")
  gains = lambda paths, key: " and ".join(
    _pm(_load(p)["final"][key]["true_gain"], _load(p)["final"][key]["true_gain_stderr"], "+")
    for p in paths)
  shares = " and ".join(f"{_load(p)['share_of_true_environment_gain']:.3f}" for p in grid)
  caption = (
    "The true gain over the cloned policy after three rounds, on held-out start states. Gridworld "
    "(2-core AMD EPYC VM, 2026-11-26), seeds 0 and 1: improved in the world model "
    f"{gains(grid, 'world_model')} px, {shares} times the gain of the same procedure in the true "
    "gridworld.\nPush-T in the `cpu` profile's world model (2-core AMD EPYC VM, 2026-11-27): "
    f"{gains(model, 'world_model')} coverage, against {gains(true, 'true_environment')} improved "
    "in gym-pusht.")
  return _section("Policy improvement", caption, image, _rel(*grid, *model, *true),
                  ["experiments/improve/RESULTS.md"])


def _bars(ax, labels: list[str], values: list[float], colours: list[str]):
  """Horizontal bars, first label on top, each with its value written beside it."""
  ax.barh(range(len(values)), values, color=colours)
  ax.set_yticks(range(len(values)), labels, fontsize=7)
  ax.invert_yaxis()
  for i, value in enumerate(values):
    ax.text(value, i, f" {value:.1f}", va="center", fontsize=7)
  ax.set_xlim(0, max(values) * 1.15)


def train_mfu(out: pathlib.Path) -> tuple[str, pathlib.Path]:
  """Training MFU per setting on one H100 and one H200, beside IRASim's PyTorch code."""
  runs = [(_load(BENCH / name), label) for name, label in TRAIN_SETTINGS]
  fig, ax = _figure()
  _bars(ax, [label for _, label in runs] + ["IRASim PyTorch, H100, B=8"],
        [run["mfu"] * 100 for run, _ in runs] + [IRASIM_TRAIN_MFU_PERCENT],
        ["C0" if "H100" in run["device"] else "C1" for run, _ in runs] + ["gray"])
  ax.set_title("Train-step MFU (wmjax: batch 16, bf16)", fontsize=10)
  ax.set(xlabel="MFU (% of the 989 TFLOP/s dense bf16 peak)")
  image = _save(fig, out / "train_mfu.png")
  best = lambda card: max(((r, label) for r, label in runs
                           if card in r["device"] and r["name"] == "irasim-XL/2"),
                          key=lambda run: run[0]["mfu"])
  (h100, h100_label), (h200, h200_label) = best("H100"), best("H200")
  caption = (  # the labels without their card
    f"The fastest IRASim-XL/2 train steps: {h100['mfu'] * 100:.1f} % MFU "
    f"({h100['samples_per_s']:.1f} samples/s) on one H100 ({h100_label[5:]}, 2026-11-23) and "
    f"{h200['mfu'] * 100:.1f} % ({h200['samples_per_s']:.1f} samples/s) on one H200 "
    f"({h200_label[5:]}, commit f5e8b2d, 2026-11-30), against {IRASIM_TRAIN_MFU_PERCENT} % "
    f"({IRASIM_TRAIN_SAMPLES_PER_S} samples/s) for IRASim's PyTorch code on an H100 (quoted in "
    "`benchmarks/RESULTS.md`).")
  return _section("Training throughput (MFU)", caption, image,
                  _rel(*(BENCH / name for name, _ in TRAIN_SETTINGS)), ["benchmarks/RESULTS.md"])


def rollout_speed(out: pathlib.Path) -> tuple[str, pathlib.Path]:
  """Rollout frames/s per setting on one H100, beside IRASim's PyTorch code with torch.compile."""
  runs = [(_load(BENCH / name), label) for name, label in ROLLOUTS]
  anchors = [(f"IRASim PyTorch, {calls} calls, batch 8", fps)
             for calls, fps in IRASIM_ROLLOUT_FRAMES_PER_S.items()]
  fig, ax = _figure()
  _bars(ax, [label for _, label in runs] + [label for label, _ in anchors],
        [run["rollout_frames_per_s"] for run, _ in runs] + [fps for _, fps in anchors],
        ["C0" if run["name"] == "irasim-XL/2" else "C2" for run, _ in runs] + ["gray"] * 2)
  ax.set_title("Rollouts on one H100, bf16 (calls: model calls per block)", fontsize=10)
  ax.set(xlabel="generated frames per second")
  image = _save(fig, out / "rollout_speed.png")
  by_name = {name: run for (run, _), (name, _) in zip(runs, ROLLOUTS)}
  xl10, xl59 = by_name["h100/xl-roll-10.json"], by_name["h100/xl-roll-59.json"]
  caption = (
    f"IRASim-XL/2 at batch 8 (2026-11-23): {xl10['rollout_frames_per_s']:.1f} frames/s at 10 model "
    f"calls per block and {xl59['rollout_frames_per_s']:.1f} at 59 (PNDM-50's cost), against "
    f"{IRASIM_ROLLOUT_FRAMES_PER_S[10]} and {IRASIM_ROLLOUT_FRAMES_PER_S[59]} for IRASim's PyTorch "
    "code with torch.compile (quoted in `benchmarks/RESULTS.md`). WPE-600M's temporal KV cache "
    f"takes it from {by_name['h100/wpe-roll-10-nokv.json']['rollout_frames_per_s']:.1f} to "
    f"{by_name['h100/wpe-roll-10-kv.json']['rollout_frames_per_s']:.1f} frames/s at 10 calls.")
  return _section("Rollout speed", caption, image, _rel(*(BENCH / name for name, _ in ROLLOUTS)),
                  ["benchmarks/RESULTS.md"])


def suite_history(out: pathlib.Path) -> tuple[str, pathlib.Path]:
  """The README test command's pytest seconds per run, by machine, in commit order."""
  path = BENCH / "test_suite_history.json"
  runs = _load(path)
  fig, ax = _figure()
  for i, machine in enumerate(dict.fromkeys(r["machine"] for r in runs)):
    for failed in (False, True):
      xs = [j for j, r in enumerate(runs)
            if r["machine"] == machine and bool(r["failed"]) == failed]
      ax.scatter(xs, [runs[j]["seconds"] for j in xs], s=14, color=f"C{i}",
                 marker="x" if failed else "o", label=None if failed else machine)
  ax.scatter([], [], s=14, marker="x", color="black", label="a run with failures")
  ax.axhline(TEST_BUDGET_S, color="gray", ls="--", label=f"{TEST_BUDGET_S} s budget")
  dates = sorted({r["date"] for r in runs})
  spans = [[j for j, r in enumerate(runs) if r["date"] == date] for date in dates]
  for span in spans[1:]:
    ax.axvline(span[0] - 0.5, color="lightgray", lw=0.5)
  ax.set_xticks([(span[0] + span[-1]) / 2 for span in spans], [d[5:] for d in dates], fontsize=7)
  ax.set_title("Test suite (README command), one point per run", fontsize=10)
  ax.set(xlabel="run, in commit order, by date (2026)", ylabel="pytest wall time (s)",
         ylim=(0, None))
  ax.legend(fontsize=6)
  image = _save(fig, out / "test_suite_history.png")
  first, fastest, last = runs[0], min(runs, key=lambda r: r["seconds"]), runs[-1]
  line = lambda r: (f"{r['seconds']:g} s at {r['commit']} ({r['date']}, {r['machine']}, "
                    f"{r['passed']} passed, {r['failed']} failed)")
  caption = (
    "Every full run of the README test command that `benchmarks/RESULTS.md` records as alone, "
    f"transcribed into JSON: from {line(first)}, through the fastest, {line(fastest)}, to the "
    f"latest, {line(last)}.\nThe machine moves the time as much as the code: compare points of "
    "one colour.")
  return _section("Test-suite wall time", caption, image, _rel(path), ["benchmarks/RESULTS.md"])


def _section(title: str, caption: str, image: pathlib.Path, files: str,
             results: list[str]) -> tuple[str, pathlib.Path]:
  """A section of the page (its caption, image, and where its data and its account are) and the
  image it links."""
  documented = " and ".join(f"`{r}`" for r in results)
  return (f"## {title}\n\n{caption}\n\n![{image.stem.replace('_', ' ')}]"
          f"({(ASSETS / image.name).as_posix()})\n\nData: {files}. Documented in {documented}.\n",
          image)


SECTIONS = [pusht_curve, policy_values, improvement, train_mfu, rollout_speed, suite_history]


def write_results_page(out_dir: pathlib.Path) -> list[pathlib.Path]:
  """Writes ``out_dir/results.md`` and its plots under ``out_dir/assets/results``; returns the
  files written, the page first."""
  assets = out_dir / ASSETS
  assets.mkdir(parents=True, exist_ok=True)
  parts = ["# Results\n\nGenerated by `python docs/make_results.py` from the results JSON the "
           "RESULTS files cite; do not edit by hand (`tests/test_results_page.py` checks that "
           "the page matches its data). Values are rounded to 3 decimals, percentages and rates "
           "to 1.\n"]
  images = []
  for section in SECTIONS:
    text, image = section(assets)
    parts.append(text)
    images.append(image)
  page = out_dir / "results.md"
  page.write_text("\n".join(parts))
  return [page] + images


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", type=pathlib.Path, default=ROOT / "docs",
                      help="folder for results.md and assets/results/ (default: docs/)")
  for path in write_results_page(parser.parse_args().out):
    print(path)


if __name__ == "__main__":
  main()
