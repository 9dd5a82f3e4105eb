"""Two policy evaluations of the same start states, compared episode by episode.

    python experiments/pusht/paired.py A/policy_eval.json B/policy_eval.json [--out table.md]

A and B are ``wmjax eval-policy`` results of two world models (a screened knob and its
baseline) from the same held-out start states. Per policy it prints, A against B, the paired
difference (mean ± standard error over episodes) of the T's IoU and angle error at the last
step, and each model's bias: its imagined value less the simulator's, per episode. Pearson with
its 95 % interval heads each table.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from wmjax.eval.metrics import mean_stderr


def _cell(values: np.ndarray, digits: int) -> str:
  """``mean ± standard error`` of ``values`` over episodes, NaNs (no T drawn) left out."""
  mean, stderr = mean_stderr(values)
  return f"{mean:+.{digits}f} ± {stderr:.{digits}f}"


def _end(result: dict, policy: str, metric: str) -> np.ndarray:
  return np.asarray(result["policies"][policy]["block"]["world_model"]["end_per_episode"][metric],
                    float)


def _bias(result: dict, policy: str) -> np.ndarray:
  coverage = result["policies"][policy]["coverage"]
  return (np.asarray(coverage["world_model"]["per_episode"], float)
          - np.asarray(coverage["simulator_reward"]["per_episode"], float))


def paired_table(a: dict, b: dict) -> str:
  """Markdown: the paired differences of evaluation ``a`` against ``b`` (module doc)."""
  if a.get("seed") != b.get("seed") or set(a["policies"]) != set(b["policies"]):
    raise ValueError("the two evaluations must share their start states (seed) and policies")
  lines = []
  for name, result in (("A", a), ("B", b)):
    coverage = result["rewards"]["coverage"]
    lo, hi = coverage["agreement_ci95"]["pearson"]
    lines.append(f"{name}: Pearson {coverage['agreement']['pearson']:.3f} [{lo:.3f}, {hi:.3f}], "
                 f"Spearman {coverage['agreement']['spearman']:.2f}")
  lines += ["", "| policy | T IoU A / B | A - B | T angle error A / B (deg) | A - B | "
            "value bias A | value bias B |", "|---|---|---|---|---|---|---|"]
  for policy in a["policies"]:
    iou_a, iou_b = _end(a, policy, "block_iou"), _end(b, policy, "block_iou")
    ang_a = _end(a, policy, "block_angle_error_deg")  # NaN where a model drew no T
    ang_b = _end(b, policy, "block_angle_error_deg")
    lines.append(
        f"| {policy} | {iou_a.mean():.3f} / {iou_b.mean():.3f} | {_cell(iou_a - iou_b, 3)} | "
        f"{np.nanmean(ang_a):.1f} / {np.nanmean(ang_b):.1f} | {_cell(ang_a - ang_b, 1)} | "
        f"{_cell(_bias(a, policy), 3)} | {_cell(_bias(b, policy), 3)} |")
  return "\n".join(lines)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("a", help="policy_eval.json of the model screened")
  parser.add_argument("b", help="policy_eval.json of its baseline (the same start states)")
  parser.add_argument("--out", help="also write the table here")
  args = parser.parse_args()
  with open(args.a) as f, open(args.b) as g:
    table = paired_table(json.load(f), json.load(g))
  print(table)
  if args.out:
    with open(args.out, "w") as f:
      f.write(table + "\n")


if __name__ == "__main__":
  main()
