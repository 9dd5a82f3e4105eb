"""benchmarks/hlo_ops.py: transpose / copy / slice kernels of optimized HLO, loop bodies counted
once per iteration, bytes of slices counted as the slice."""

import sys

import pytest

from conftest import ROOT

pytestmark = pytest.mark.unit

sys.path.insert(0, str(ROOT / "benchmarks"))
import hlo_ops  # noqa: E402

# A loop of 5 iterations that transposes an f32[8,4] (a transpose fusion), scales it (a fusion
# with a transpose inside that is not its root), stacks a row into f32[5,4,8] (a dynamic-update-
# slice fusion that runs as a memcpy) and copies it to another layout; after the loop one plain copy. HLO text has one
# instruction a line: the lines continued here (indented 6) are joined below.
MODULE = """HloModule m

%fused_transpose (param_0: f32[8,4]) -> f32[4,8] {
  %param_0 = f32[8,4]{1,0} parameter(0)
  %transpose.1 = f32[4,8]{1,0} transpose(%param_0), dimensions={1,0}
  ROOT %convert.1 = f32[4,8]{1,0} convert(%transpose.1)
}

%fused_scale (param_0.1: f32[8,4]) -> f32[4] {
  %param_0.1 = f32[8,4]{1,0} parameter(0)
  %transpose.2 = f32[4,8]{1,0} transpose(%param_0.1), dimensions={1,0}
  %constant.1 = f32[] constant(0)
  ROOT %reduce.1 = f32[4]{0} reduce(%transpose.2, %constant.1), dimensions={1}, to_apply=%add
}

%fused_dus (param_0.2: f32[5,4,8], param_1.2: f32[4,8], param_2.2: s32[]) -> f32[5,4,8] {
  %param_0.2 = f32[5,4,8]{2,1,0} parameter(0)
  %param_1.2 = f32[4,8]{1,0} parameter(1)
  %bitcast.1 = f32[1,4,8]{2,1,0} bitcast(%param_1.2)
  %param_2.2 = s32[] parameter(2)
  %constant.2 = s32[] constant(0)
  ROOT %dus.1 = f32[5,4,8]{2,1,0} dynamic-update-slice(%param_0.2, %bitcast.1, %param_2.2,
      %constant.2, %constant.2)
}

%add (a: f32[], b: f32[]) -> f32[] {
  %a = f32[] parameter(0)
  %b = f32[] parameter(1)
  ROOT %sum = f32[] add(%a, %b)
}

%body (p: (s32[], f32[8,4], f32[5,4,8])) -> (s32[], f32[8,4], f32[5,4,8]) {
  %p = (s32[], f32[8,4]{1,0}, f32[5,4,8]{2,1,0}) parameter(0)
  %i = s32[] get-tuple-element(%p), index=0
  %x = f32[8,4]{1,0} get-tuple-element(%p), index=1
  %stack = f32[5,4,8]{2,1,0} get-tuple-element(%p), index=2
  %fusion.1 = f32[4,8]{1,0} fusion(%x), kind=kInput, calls=%fused_transpose,
      metadata={op_name="jit(f)/while/body/layers/attn/transpose"}
  %fusion.2 = f32[4]{0} fusion(%x), kind=kInput, calls=%fused_scale,
      metadata={op_name="jit(f)/while/body/layers/scale"}
  %fusion.3 = f32[5,4,8]{2,1,0} fusion(%stack, %fusion.1, %i), kind=kCustom, calls=%fused_dus,
      metadata={op_name="jit(f)/while/body/dynamic_update_slice"},
      backend_config={"fusion_backend_config":{"kind":"__custom_fusion",
      "custom_fusion_config":{"name":"dynamic_slice_fusion","kernel_index":0}}}
  %copy.1 = f32[8,4]{0,1} copy(%x)
  ROOT %t = (s32[], f32[8,4]{1,0}, f32[5,4,8]{2,1,0}) tuple(%i, %x, %fusion.3)
}

%cond (p.1: (s32[], f32[8,4], f32[5,4,8])) -> pred[] {
  %p.1 = (s32[], f32[8,4]{1,0}, f32[5,4,8]{2,1,0}) parameter(0)
  ROOT %c = pred[] constant(true)
}

ENTRY %main (x.1: f32[8,4], s.1: f32[5,4,8]) -> f32[5,4,8] {
  %x.1 = f32[8,4]{1,0} parameter(0)
  %s.1 = f32[5,4,8]{2,1,0} parameter(1)
  %zero = s32[] constant(0)
  %init = (s32[], f32[8,4]{1,0}, f32[5,4,8]{2,1,0}) tuple(%zero, %x.1, %s.1)
  %while.1 = (s32[], f32[8,4]{1,0}, f32[5,4,8]{2,1,0}) while(%init), condition=%cond,
      body=%body, backend_config={"known_trip_count":{"n":"5"}}
  %out = f32[5,4,8]{2,1,0} get-tuple-element(%while.1), index=2
  ROOT %copy.2 = f32[5,4,8]{2,1,0} copy(%out)
}
""".replace("\n      ", " ")


def test_kernels_are_classified_and_loop_bodies_counted_per_iteration():
  rows = {(row.cls, row.op): row for row in hlo_ops.analyze(MODULE)}
  tile = 8 * 4 * 4  # bytes of one f32[8,4]
  transpose = rows["transpose", "layers/attn/transpose"]
  assert (transpose.count, transpose.moved) == (5, 5 * 2 * tile)
  layout_copy = rows["transpose", "?"]  # the copy to layout {0,1}
  assert (layout_copy.count, layout_copy.moved) == (5, 5 * 2 * tile)
  scale = rows["transposing", "layers/scale"]
  assert (scale.count, scale.moved) == (5, 5 * 2 * tile)
  stack = rows["memcpy", "dynamic_update_slice"]  # the row written, not the whole stack
  assert (stack.count, stack.moved) == (5, 5 * 2 * tile)
  memcpy = rows["copy", "?"]
  assert (memcpy.count, memcpy.moved) == (1, 2 * 5 * tile)
  summary = hlo_ops.summary(list(rows.values()))
  assert summary["total"]["kernels"] == 21
  assert summary["transpose"]["gb"] == pytest.approx(20 * tile / 1e9)
