"""benchmarks/profile_ops.py: device time by op from a Perfetto trace, each op counted once."""

import gzip
import json
import sys

import pytest

from conftest import ROOT

pytestmark = pytest.mark.unit

sys.path.insert(0, str(ROOT / "benchmarks"))
import profile_ops  # noqa: E402


def _meta(kind, pid, name, tid=None):
  event = {"ph": "M", "name": kind, "pid": pid, "args": {"name": name}}
  return event if tid is None else dict(event, tid=tid)


def _op(pid, tid, name, dur_us):
  return {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": 0, "dur": dur_us}


def test_gpu_trace_counts_the_xla_ops_line_once(tmp_path):
  events = [
      _meta("process_name", 1, "/host:CPU"), _meta("process_name", 7, "/device:GPU:0 H100"),
      _meta("thread_name", 7, "XLA Modules", 1), _meta("thread_name", 7, "XLA Ops", 2),
      _meta("thread_name", 7, "Stream #13(Compute)", 3),
      _op(7, 1, "jit_step", 10_000),                           # the whole program: not an op
      _op(7, 2, "nvjet_sm90_tst_144x128", 6_000), _op(7, 2, "fusion_12", 2_000),
      _op(7, 2, "cudnn_generated_fort_native_sdpa_sm90_flash_fprop", 1_500),
      _op(7, 2, "memcpy128", 500),
      _op(7, 3, "nvjet_sm90_tst_144x128", 6_000),              # the same kernel on its stream
      _op(1, 9, "$api.py block_until_ready", 50_000),          # host Python
  ]
  path = tmp_path / "perfetto_trace.json.gz"
  with gzip.open(path, "wt") as f:
    json.dump({"traceEvents": events}, f)
  summary = profile_ops.summarize_trace(str(path), calls=2)
  assert summary["device_ms_per_call"] == pytest.approx(5.0)   # 10 ms of ops over 2 calls
  assert summary["by_class"] == pytest.approx(
      {"matmul": 3.0, "elementwise": 1.0, "attention": 0.75, "copy": 0.25})
  assert [row["op"] for row in summary["top_ops"]][:2] == ["nvjet_sm90_tst_144x128", "fusion_12"]
