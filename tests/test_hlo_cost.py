"""wmjax.train.hlo_cost: every kernel of optimized HLO in its class (matmuls, attention, Pallas
kernels, transposes, copies, slices, reductions, elementwise, collectives), loop bodies counted
once per iteration, bytes of slices counted as the slice, FLOPs of matmuls."""

import jax
import jax.numpy as jnp
import pytest

from wmjax.train import fit, hlo_cost

pytestmark = pytest.mark.unit

# A loop of 5 iterations that transposes an f32[8,4] (a transpose fusion), scales it (a fusion
# with a transpose inside that is not its root), stacks a row into f32[5,4,8] (a dynamic-update-
# slice fusion that runs as a memcpy), reads a row back (a dynamic-slice memcpy, copied at its
# root), copies the f32[8,4] to another layout, multiplies it by its transpose (cuBLAS, with a
# workspace in its output) and runs a Pallas kernel on it. After the loop: cuDNN attention, a
# Triton GEMM fusion that transposes inside, an elementwise and a reduction fusion, an all-reduce
# (whose reducer is no kernel) and one plain copy. HLO text has one instruction a line: the lines
# continued here (indented 6) are joined below.
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

%fused_ds (param_0.3: f32[5,4,8], param_1.3: s32[]) -> f32[1,4,8] {
  %param_0.3 = f32[5,4,8]{2,1,0} parameter(0)
  %param_1.3 = s32[] parameter(1)
  %constant.3 = s32[] constant(0)
  %ds.1 = f32[1,4,8]{2,1,0} dynamic-slice(%param_0.3, %param_1.3, %constant.3, %constant.3),
      dynamic_slice_sizes={1,4,8}
  ROOT %copy.3 = f32[1,4,8]{2,1,0} copy(%ds.1)
}

%fused_gemm (param_0.4: f32[8,4], param_1.4: f32[8,4]) -> f32[8,8] {
  %param_0.4 = f32[8,4]{1,0} parameter(0)
  %param_1.4 = f32[8,4]{1,0} parameter(1)
  %transpose.3 = f32[4,8]{1,0} transpose(%param_1.4), dimensions={1,0}
  ROOT %dot.1 = f32[8,8]{1,0} dot(%param_0.4, %transpose.3), lhs_contracting_dims={1},
      rhs_contracting_dims={0}
}

%fused_gelu (param_0.5: f32[8,4]) -> f32[8,4] {
  %param_0.5 = f32[8,4]{1,0} parameter(0)
  ROOT %tanh.1 = f32[8,4]{1,0} tanh(%param_0.5)
}

%fused_rowsum (param_0.6: f32[8,4]) -> f32[8] {
  %param_0.6 = f32[8,4]{1,0} parameter(0)
  %constant.6 = f32[] constant(0)
  ROOT %reduce.2 = f32[8]{0} reduce(%param_0.6, %constant.6), dimensions={1}, to_apply=%add
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
  %fusion.4 = f32[1,4,8]{2,1,0} fusion(%stack, %i), kind=kCustom, calls=%fused_ds,
      metadata={op_name="jit(f)/while/body/dynamic_slice"},
      backend_config={"fusion_backend_config":{"kind":"__custom_fusion",
      "custom_fusion_config":{"name":"dynamic_slice_fusion","kernel_index":0}}}
  %copy.1 = f32[8,4]{0,1} copy(%x)
  %gemm = (f32[8,8]{1,0}, s8[1024]{0}) custom-call(%x, %fusion.1),
      custom_call_target="__cublas$lt$matmul",
      metadata={op_name="jit(f)/while/body/layers/mlp/dot_general"},
      backend_config={"gemm_backend_config":{"dot_dimension_numbers":{
      "lhs_contracting_dimensions":["1"],"rhs_contracting_dimensions":["0"]}}}
  %pallas = f32[8,4]{1,0} custom-call(%x), custom_call_target="__gpu$xla.gpu.triton",
      api_version=API_VERSION_TYPED_FFI,
      metadata={op_name="jit(f)/while/body/layers/mlp/wmjax_dense_gelu/pallas_call"},
      backend_config={debug = false, ir = "ML\\EFR", name = "wmjax_dense_gelu", num_warps = 4 : i32}
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
  %q = f32[1,4,8]{2,1,0} bitcast(%x.1)
  %attn = (f32[1,4,8]{2,1,0}, f32[1,4]{1,0}, u8[0]{0}) custom-call(%q, %q, %q),
      custom_call_target="__cudnn$fmhaSoftmax", metadata={op_name="jit(f)/attn/fmha"},
      backend_config={"cudnn_fmha_backend_config":{"intermediate_tensor_shape":{"element_type":
      "F32","dimensions":["1","1","4","4"]}}}
  %qk = f32[8,8]{1,0} fusion(%x.1, %x.1), kind=kCustom, calls=%fused_gemm,
      metadata={op_name="jit(f)/attn/qk"},
      backend_config={"fusion_backend_config":{"kind":"__triton_gemm"}}
  %gelu = f32[8,4]{1,0} fusion(%x.1), kind=kLoop, calls=%fused_gelu,
      metadata={op_name="jit(f)/mlp/gelu"}
  %rowsum = f32[8]{0} fusion(%gelu), kind=kInput, calls=%fused_rowsum,
      metadata={op_name="jit(f)/norm/reduce_sum"}
  %ar = f32[8,4]{1,0} all-reduce(%gelu), replica_groups={}, to_apply=%add,
      metadata={op_name="jit(f)/psum"}
  ROOT %copy.2 = f32[5,4,8]{2,1,0} copy(%out)
}
""".replace("\n      ", " ")


def test_kernels_are_classified_and_loop_bodies_counted_per_iteration():
  rows = {(row.cls, row.op): row for row in hlo_cost.analyze(MODULE)}
  tile = 8 * 4 * 4  # bytes of one f32[8,4] (or f32[4,8], f32[1,4,8])
  transpose = rows["transpose", "layers/attn/transpose"]
  assert (transpose.count, transpose.moved) == (5, 5 * 2 * tile)
  layout_copy = rows["transpose", "?"]  # the copy to layout {0,1}
  assert (layout_copy.count, layout_copy.moved) == (5, 5 * 2 * tile)
  scale = rows["transposing", "layers/scale"]  # reads f32[8,4], writes f32[4]
  assert (scale.count, scale.moved) == (5, 5 * (tile + 16))
  stack = rows["memcpy", "dynamic_update_slice"]  # the row written, not the whole stack
  assert (stack.count, stack.moved) == (5, 5 * 2 * tile)
  row = rows["memcpy", "dynamic_slice"]  # the row read, not the whole stack
  assert (row.count, row.moved) == (5, 5 * 2 * tile)
  memcpy = rows["copy", "?"]
  assert (memcpy.count, memcpy.moved) == (1, 2 * 5 * tile)
  gemm = rows["matmul", "layers/mlp/dot_general"]  # writes f32[8,8], not its s8 workspace
  assert (gemm.count, gemm.moved, gemm.flops) == (5, 5 * 4 * tile, 5 * 2 * 8 * 8 * 4)
  qk = rows["matmul", "attn/qk"]  # a GEMM fusion, though it transposes inside
  assert (qk.count, qk.moved, qk.flops) == (1, 4 * tile, 2 * 8 * 8 * 4)
  pallas = rows["pallas", "wmjax_dense_gelu"]
  assert (pallas.count, pallas.moved) == (5, 5 * 2 * tile)
  fmha = rows["attention", "attn/fmha"]  # Q K^T and P V over 4 x 4 scores of head dim 8
  assert (fmha.moved, fmha.flops) == (3 * tile + tile + 16, 2 * (2 * 4 * 4 * 8))
  assert rows["elementwise", "mlp/gelu"].moved == 2 * tile
  assert rows["reduction", "norm/reduce_sum"].moved == tile + 32
  assert rows["collective", "psum"].moved == 2 * tile
  assert not any(cls == "other" for cls, _ in rows)  # the all-reduce's reducer is no kernel
  summary = hlo_cost.summary(list(rows.values()))
  assert summary["total"]["kernels"] == 41
  assert summary["outside matmul"]["kernels"] == 35
  assert summary["transpose"]["gb"] == pytest.approx(20 * tile / 1e9)
  assert summary["matmul"]["tflop"] == pytest.approx(6 * 512 / 1e12)


def test_a_scanned_step_costs_what_the_unrolled_one_does():
  """XLA's own cost analysis counts a loop body once; the step's cost counts it per iteration, so
  ten matmuls in a ``lax.scan`` cost what ten written out do."""
  x, w = jnp.ones((64, 64)), jnp.ones((10, 64, 64))

  def scanned(x, w):
    return jax.lax.scan(lambda h, wi: (jnp.tanh(h @ wi), None), x, w)[0]

  def unrolled(x, w):
    for i in range(10):
      x = jnp.tanh(x @ w[i])
    return x

  costs = [hlo_cost.step_cost(jax.jit(f).lower(x, w).compile().as_text())
           for f in (scanned, unrolled)]
  assert costs[0]["matmul_flops"] == costs[1]["matmul_flops"] == 10 * 2 * 64 ** 3
  assert costs[0]["other_bytes"] >= 10 * 2 * 64 * 64 * 4  # each tanh reads and writes a tile


def test_a_tpu_matmul_compiled_as_a_convolution_counts_its_flops():
  """TPUs compile a matmul to a ``convolution`` (here [4, 3, 32] from a 32 x 32 kernel, inside a
  fusion): 2 x output elements x the kernel's elements per output feature."""
  module = """HloModule m

%fused_proj (p0: f32[4,3,32], p1: f32[32,32]) -> f32[4,3,32] {
  %p0 = f32[4,3,32]{2,1,0} parameter(0)
  %p1 = f32[32,32]{1,0} parameter(1)
  ROOT %convolution.1 = f32[4,3,32]{2,1,0} convolution(%p0, %p1), window={size=1}, dim_labels=b0f_io->b0f
}

ENTRY %main (x: f32[4,3,32], w: f32[32,32]) -> f32[4,3,32] {
  %x = f32[4,3,32]{2,1,0} parameter(0)
  %w = f32[32,32]{1,0} parameter(1)
  ROOT %proj = f32[4,3,32]{2,1,0} fusion(%x, %w), kind=kOutput, calls=%fused_proj
}
"""
  cost = hlo_cost.step_cost(module)
  assert cost["matmul_flops"] == 2 * (4 * 3 * 32) * 32


def test_a_float8_gemm_counts_apart_and_is_priced_at_twice_the_matmul_rate():
  """A cuBLAS float8 GEMM (what XLA makes of :mod:`wmjax.nn.float8`'s matmul on a Hopper card):
  its FLOPs count among the matmuls' and apart, and the step's predicted time gives them half
  the time of bf16 FLOPs."""
  module = """HloModule m

ENTRY %main (x: f8e4m3fn[64,32], w: f8e4m3fn[16,32], a: bf16[64,32], b: bf16[32,16]) -> bf16[64,16] {
  %x = f8e4m3fn[64,32]{1,0} parameter(0)
  %w = f8e4m3fn[16,32]{1,0} parameter(1)
  %a = bf16[64,32]{1,0} parameter(2)
  %b = bf16[32,16]{1,0} parameter(3)
  %one = f32[] constant(1)
  %fp8 = (bf16[64,16]{1,0}, s8[1024]{0}) custom-call(%x, %w, %one, %one),
      custom_call_target="__cublas$lt$matmul$f8", metadata={op_name="jit(f)/mlp/fc1/dot_general"},
      backend_config={"gemm_backend_config":{"dot_dimension_numbers":{
      "lhs_contracting_dimensions":["1"],"rhs_contracting_dimensions":["1"]}}}
  %bf16 = (bf16[64,16]{1,0}, s8[1024]{0}) custom-call(%a, %b),
      custom_call_target="__cublas$lt$matmul", metadata={op_name="jit(f)/mlp/fc2/dot_general"},
      backend_config={"gemm_backend_config":{"dot_dimension_numbers":{
      "lhs_contracting_dimensions":["1"],"rhs_contracting_dimensions":["0"]}}}
  %y = bf16[64,16]{1,0} get-tuple-element(%fp8), index=0
  ROOT %z = bf16[64,16]{1,0} get-tuple-element(%bf16), index=0
}
""".replace("\n      ", " ")
  flops = 2 * 64 * 16 * 32
  rows = {row.cls: row for row in hlo_cost.analyze(module)}
  assert rows["matmul_fp8"].flops == rows["matmul"].flops == flops
  cost = hlo_cost.step_cost(module)
  assert (cost["matmul_flops"], cost["fp8_matmul_flops"]) == (2 * flops, flops)
  rates = (1e12, 1e9)
  bf16_only = dict(cost, fp8_matmul_flops=0.0)
  assert fit.predicted_step_s(cost, rates) == pytest.approx(
      fit.predicted_step_s(bf16_only, rates) - 0.5 * flops / (fit.MATMUL_EFFICIENCY * 1e12))
