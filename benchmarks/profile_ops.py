"""Device-time breakdown of a jitted function from a ``jax.profiler`` trace.

``top_ops(fn, calls, log_dir)`` runs ``fn`` ``calls`` times under ``jax.profiler.trace`` (after the
caller has compiled and warmed it), reads the Perfetto trace that JAX writes beside the XPlane
file, and sums the duration of every event on the accelerator's streams by name (XLA fusions,
cuBLAS / cuDNN kernels; on CPU the host's XLA ops). Each op also gets a coarse class
(``matmul``, ``attention``, ``transpose``, ``reduction``, ``elementwise``, ``collective``,
``copy``, ``other``) from its name, so that a table says where the step's time goes.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import re

import jax

# (class, pattern over the lower-cased op / kernel name); the first match wins.
_CLASSES = (
    ("attention", r"fmha|flash|attention|softmax|cudnn\$fmha|splash"),
    ("collective", r"all-reduce|all-gather|reduce-scatter|all-to-all|collective|nccl"),
    ("matmul", r"gemm|dot|cublas|cutlass|xmma|nvjet|matmul|conv"),
    ("transpose", r"transpose|copy_fusion|bitcast"),
    ("reduction", r"reduce"),
    ("copy", r"copy|memcpy|memset|dynamic-update-slice|dynamic_update_slice"),
    ("elementwise", r"fusion|loop_|add|multiply|convert|select|exp|tanh"),
)


def op_class(name: str) -> str:
  low = name.lower()
  for cls, pattern in _CLASSES:
    if re.search(pattern, low):
      return cls
  return "other"


def _op_lines(events: list[dict]) -> set[tuple[int, int]]:
  """(pid, tid) of the trace lines that hold one event per executed XLA op.

  On an accelerator: the device's "XLA Ops" line (its "XLA Modules" line spans whole programs and
  would count everything twice), or its "Stream" lines where there is no such line. On CPU: the
  host's XLA op events are picked by name in :func:`summarize_trace`, so every line is kept.
  """
  meta = lambda kind: {(e["pid"], e.get("tid")): e.get("args", {}).get("name", "")
                       for e in events if e.get("ph") == "M" and e.get("name") == kind}
  processes = {pid: name for (pid, _), name in meta("process_name").items()}
  threads = meta("thread_name")
  device = {pid for pid, name in processes.items() if name.startswith("/device:")}
  if not device:
    return {(e.get("pid"), e.get("tid")) for e in events}
  ops = {key for key, name in threads.items() if key[0] in device and name == "XLA Ops"}
  return ops or {key for key, name in threads.items()
                 if key[0] in device and name.startswith("Stream")}


def _is_host_bookkeeping(name: str) -> bool:
  return name.startswith("$") or "Execute" in name or name.startswith("Thunk")


def summarize_trace(path: str, calls: int, top: int = 25) -> dict:
  """Per-call device milliseconds by op name and by class, from a ``perfetto_trace.json.gz``."""
  with gzip.open(path, "rt") as f:
    trace = json.load(f)
  events = trace["traceEvents"] if isinstance(trace, dict) else trace
  lines = _op_lines(events)
  by_name: dict[str, float] = collections.Counter()
  for e in events:
    if (e.get("ph") == "X" and (e.get("pid"), e.get("tid")) in lines and "dur" in e
        and not _is_host_bookkeeping(e["name"])):
      by_name[e["name"]] += float(e["dur"]) / 1e3 / calls  # µs -> ms per call
  total = sum(by_name.values())
  by_class: dict[str, float] = collections.Counter()
  for name, ms in by_name.items():
    by_class[op_class(name)] += ms
  rows = [{"op": name, "class": op_class(name), "ms": ms, "share": ms / total if total else 0.0}
          for name, ms in sorted(by_name.items(), key=lambda kv: -kv[1])[:top]]
  return {"device_ms_per_call": total, "calls": calls,
          "by_class": {k: v for k, v in sorted(by_class.items(), key=lambda kv: -kv[1])},
          "top_ops": rows}


def top_ops(fn, calls: int, log_dir: str, top: int = 25) -> dict:
  """Trace ``calls`` calls of the (already compiled) ``fn`` and summarise the device time."""
  os.makedirs(log_dir, exist_ok=True)
  with jax.profiler.trace(log_dir, create_perfetto_trace=True):
    for _ in range(calls):
      jax.block_until_ready(fn())
  traces = sorted(glob.glob(os.path.join(log_dir, "**", "perfetto_trace.json.gz"), recursive=True),
                  key=os.path.getmtime)
  if not traces:
    raise RuntimeError(f"jax.profiler wrote no perfetto_trace.json.gz under {log_dir}")
  return summarize_trace(traces[-1], calls, top)


def format_table(summary: dict) -> str:
  lines = [f"device time per call: {summary['device_ms_per_call']:.2f} ms",
           "by class: " + ", ".join(f"{k} {v:.2f} ms" for k, v in summary["by_class"].items()),
           f"{'ms':>9}  {'share':>6}  {'class':<11} op"]
  for row in summary["top_ops"]:
    lines.append(f"{row['ms']:9.3f}  {row['share']:6.1%}  {row['class']:<11} {row['op'][:90]}")
  return "\n".join(lines)
