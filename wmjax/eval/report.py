"""The results of ``wmjax evaluate`` as a Markdown report and as JSON."""

from __future__ import annotations

from typing import Any

import numpy as np

from wmjax.eval.metrics import LOWER_IS_BETTER
from wmjax.registry import FrameMetrics


def _cell(entry: dict, digits: int = 4) -> str:
  if not np.isfinite(entry["stderr"]):
    return f"{entry['mean']:.{digits}g}"
  return f"{entry['mean']:.{digits}g} ± {entry['stderr']:.2g}"


def markdown_report(results: dict, header: str, task: FrameMetrics | None = None) -> str:
  """The results as Markdown tables: IRASim short / long (model vs copy-last, per-frame curves
  of the task's headline metric, else MSE) and the WPE sweep; ``task`` adds the dataset's own
  metrics."""
  order = dict(LOWER_IS_BETTER, **(task.lower_is_better if task else {}))
  lines = [header, ""]
  for name, title in (("short", "IRASim short trajectories"), ("long", "IRASim long trajectories")):
    if name not in results:
      continue
    r = results[name]
    lines += [f"## {title} (c={r['context']}, h={r['horizon']}, {r['trajectories']} "
              f"trajectories)", "", "| metric | model | copy last frame | better |",
              "|---|---|---|---|"]
    for metric, lower in order.items():
      if metric in r["model"]:
        m, b = r["model"][metric], r["copy_last"][metric]
        better = "model" if (m["mean"] < b["mean"]) == lower else "copy-last"
        lines.append(f"| {metric}{' ↓' if lower else ' ↑'} | {_cell(m)} | {_cell(b)} | {better} |")
    for reason in r.get("left_out", ()):
      lines += ["", f"{reason}."]
    key = task.headline if task and task.headline in r["model"] else "mse"
    curve, base = r["model"][key]["per_frame"], r["copy_last"][key]["per_frame"]
    shown = np.unique(np.linspace(0, len(curve) - 1, min(len(curve), 16)).round().astype(int))
    lines += ["", f"{key} per generated frame (model / copy-last):", "",
              "| frame | " + " | ".join(str(i + 1) for i in shown) + " |",
              "|---" * (len(shown) + 1) + "|",
              "| model | " + " | ".join(f"{curve[i]:.3g}" for i in shown) + " |",
              "| copy last | " + " | ".join(f"{base[i]:.3g}" for i in shown) + " |", ""]
  if "sweep" in results:
    rows = results["sweep"]["rows"]
    names = [m for m in order if m in rows[0]]
    lines += [f"## WPE context / horizon sweep ({results['sweep']['target_frames']} target "
              f"frames, mean ± stderr over {rows[0]['sets']} sets)", "",
              "| c | h | " + " | ".join(names) + " |", "|---|---" + "|---" * len(names) + "|"]
    for row in rows:
      lines.append(f"| {row['context']} | {row['horizon']} | "
                   + " | ".join(_cell(row[n]) for n in names) + " |")
    copy = rows[0]["copy_last"]
    lines.append("| copy last | | " + " | ".join(f"{copy[n]:.4g}" for n in names) + " |")
  return "\n".join(lines) + "\n"


def to_json_safe(value: Any) -> Any:
  """NaN / inf -> None, recursively (JSON has no NaN)."""
  if isinstance(value, dict):
    return {k: to_json_safe(v) for k, v in value.items()}
  if isinstance(value, (list, tuple)):
    return [to_json_safe(v) for v in value]
  if isinstance(value, float) and not np.isfinite(value):
    return None
  return value
