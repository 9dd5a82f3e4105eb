"""The ST-DiT: sizes, per-frame conditioning, sharding annotations, FLOPs and input checks."""

import json

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.sharding import NamedSharding, PartitionSpec

from conftest import ROOT, jit_apply, perturbed, tiny_config
from wmjax.config import load_config
from wmjax.model import WorldModel
from wmjax.nn import STDiT, forward_flops, layers
from wmjax.nn.dit import layers_scanned, relayout_layers
from wmjax.train.checkpoint import shapes_by_path

pytestmark = pytest.mark.unit

PAPER_SIZES = [("irasim.py:S", 33e6), ("irasim.py:B", 132e6), ("irasim.py:L", 461e6),
               ("irasim.py:XL", 679e6), ("wpe_600m.py", 609e6)]


def _inputs(b, t, h, w, c, a, seed=0):
  k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
  return (jax.random.normal(k1, (b, t, h, w, c)),
          jax.random.uniform(k2, (b, t), maxval=999.0),
          jax.random.normal(k3, (b, t - 1, a)))


@pytest.mark.parametrize("spec,paper", PAPER_SIZES)
def test_parameter_counts_match_papers(spec, paper):
  config = load_config(str(ROOT / "configs" / spec))
  model = STDiT(**config.model)
  h, w, c = config.frame_shape
  x, t, a = (jax.ShapeDtypeStruct(s, jnp.float32) for s in
             [(1, model.num_frames, h, w, c), (1, model.num_frames), (1, model.num_frames - 1, 7)])
  shapes = jax.eval_shape(model.init, jax.random.key(0), x, t, a)
  count = sum(int(np.prod(p.shape)) for p in jax.tree.leaves(shapes))
  assert abs(count / paper - 1) < 0.02, f"{spec}: {count / 1e6:.1f}M vs {paper / 1e6:.0f}M"


def _model(cond="frame", **kw):
  config = tiny_config("irasim.py:S", f"model.cond={cond!r}", "model.causal_temporal=True")
  fields = dict(config.model)
  fields.update(kw)
  model = STDiT(**fields)
  x, t, a = _inputs(2, 6, 8, 8, 4, 7)
  params = perturbed(jax.jit(model.init)(jax.random.key(0), x, t, a), jax.random.key(1))
  return model, params, (x, t, a)


@pytest.mark.parametrize("cond", ["frame", "per_frame"])
@pytest.mark.slow
def test_action_j_conditions_frame_j_plus_1_only(cond):
  """Causal temporal mask: changing action j changes no frame before j+1, and does change j+1."""
  model, params, (x, t, a) = _model(cond)
  apply = jit_apply(model)
  base = apply(params, x, t, a)
  for j in range(a.shape[1]):
    out = apply(params, x, t, a.at[:, j].add(1.0))
    diff = jnp.abs(out - base).reshape(out.shape[0], out.shape[1], -1).max(-1)  # [B, T]
    assert float(diff[:, : j + 1].max()) == 0.0, f"action {j} leaked into frames <= {j}"
    assert float(diff[:, j + 1].min()) > 1e-4, f"action {j} did not change frame {j + 1}"


def test_frame_zero_and_masked_frames_use_null_embedding():
  model, params, (_, t, a) = _model("frame")
  apply = jit_apply(model)
  spatial, temporal, final = apply(params, t, a, method=STDiT.conditioning)
  temb = apply(params, t, method=lambda m, t: m.time_embed(t))
  null = params["params"]["null_action"].value
  np.testing.assert_allclose(spatial[:, 0], temb[:, 0] + null, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(temporal, temb, rtol=1e-5, atol=1e-6)  # IRASim: timestep only
  np.testing.assert_allclose(final, spatial)
  assert float(jnp.abs(spatial[:, 1:] - (temb[:, 1:] + null)).min()) > 0  # real actions differ
  mask = jnp.ones(a.shape[:2], bool).at[:, 2].set(False)
  masked, _, _ = apply(params, t, a, mask, method=STDiT.conditioning)
  np.testing.assert_allclose(masked[:, 3], temb[:, 3] + null, rtol=1e-5, atol=1e-6)
  dropped, _, _ = apply(params, t, a, None, jnp.array([True, False]), method=STDiT.conditioning)
  np.testing.assert_allclose(dropped[0], temb[0] + null, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(dropped[1], spatial[1], rtol=1e-6)


@pytest.mark.slow
def test_video_mode_conditions_every_frame_on_the_whole_trajectory():
  model, params, (x, t, a) = _model("video")
  apply = jit_apply(model)
  base = apply(params, x, t, a)
  out = apply(params, x, t, a.at[:, -1].add(1.0))  # the last action only
  diff = jnp.abs(out - base).reshape(out.shape[0], out.shape[1], -1).max(-1)
  assert float(diff.min()) > 1e-4  # even frame 0, despite the causal mask


@pytest.mark.slow
def test_trajectory_in_temporal_variant_reaches_earlier_frames():
  model, params, (x, t, a) = _model("frame", trajectory_in_temporal=True)
  apply = jit_apply(model)
  base = apply(params, x, t, a)
  out = apply(params, x, t, a.at[:, -1].add(1.0))
  assert float(jnp.abs(out - base)[:, 0].max()) > 1e-4


@pytest.mark.slow
def test_action_dropout_in_training_uses_null_embedding():
  model, params, (x, t, a) = _model("frame", action_dropout=1.0)
  apply = jit_apply(model)
  train_out = apply(params, x, t, a, train=True, rngs={"dropout": jax.random.key(0)})
  null_out = apply(params, x, t, a, None, jnp.ones((2,), bool))
  np.testing.assert_allclose(train_out, null_out, rtol=1e-6)
  assert float(jnp.abs(apply(params, x, t, a) - null_out).max()) > 1e-4


def test_parameters_carry_logical_axes():
  model, params, _ = _model("frame")
  boxed = jax.tree.leaves(params, is_leaf=lambda v: isinstance(v, nn.Partitioned))
  assert boxed and all(isinstance(v, nn.Partitioned) for v in boxed)
  specs = nn.get_partition_spec(params)["params"]
  attn = specs["blocks"]["layers"]["spatial"]["attn"]["query"]["kernel"]
  assert tuple(attn) == ("layers", "embed", "heads", "kv")
  assert tuple(specs["blocks"]["layers"]["temporal"]["mlp"]["fc1"]["kernel"]) == ("layers", "embed", "mlp")
  for box in boxed:
    assert len(box.names) == box.value.ndim


def test_world_model_init_boxes_and_plain_arrays_are_interchangeable():
  """``WorldModel.init`` returns boxed leaves, ``load_model`` plain arrays: the network takes
  either, and ``nn.unbox`` turns the one into the other."""
  wm = WorldModel.from_config(tiny_config())
  boxed = wm.init(jax.random.key(0), (8, 8, 4), frames=3)
  leaves = jax.tree.leaves(boxed, is_leaf=lambda v: isinstance(v, nn.LogicallyPartitioned))
  assert all(isinstance(v, nn.LogicallyPartitioned) for v in leaves)
  plain = nn.unbox(boxed)
  assert not any(isinstance(v, nn.Partitioned) for v in jax.tree.leaves(
      plain, is_leaf=lambda v: isinstance(v, nn.Partitioned)))
  assert jax.tree.structure(plain) == jax.tree.structure(nn.unbox(plain))
  apply = jit_apply(wm.network)
  x, t, a = _inputs(1, 3, 8, 8, 4, 7)
  np.testing.assert_array_equal(apply(boxed, x, t, a), apply(plain, x, t, a))


def test_scanned_and_unrolled_layers_agree_and_convert_both_ways():
  """relayout_layers turns a scanned model's parameters (and its optimiser state, and abstract
  arrays with shardings) into the unrolled model's and back, leaf for leaf."""
  model, params, (x, t, a) = _model("per_frame", depth=4)  # two layers
  unrolled = model.clone(scan_layers=False)
  p = nn.unbox(params)
  p_unrolled = relayout_layers(p, scan=False)
  expected = nn.unbox(jax.eval_shape(unrolled.init, jax.random.key(0), x, t, a))
  assert jax.tree.structure(p_unrolled) == jax.tree.structure(expected)
  assert layers_scanned(shapes_by_path(p)) and layers_scanned(shapes_by_path(p_unrolled)) is False
  np.testing.assert_array_equal(p_unrolled["params"]["blocks"]["layer_1"]["spatial"]["mlp"]
                                ["fc1"]["kernel"], p["params"]["blocks"]["layers"]["spatial"]
                                ["mlp"]["fc1"]["kernel"][1])
  np.testing.assert_allclose(jit_apply(unrolled)(p_unrolled, x, t, a),
                             jit_apply(model)(params, x, t, a), rtol=1e-5, atol=1e-5)
  assert jax.tree.all(jax.tree.map(lambda u, v: bool((u == v).all()),
                                   relayout_layers(p_unrolled, scan=True), p))
  assert relayout_layers(p, scan=True)["params"]["blocks"].keys() == {"layers"}  # as it was
  opt_state = optax.adam(1e-3).init(p)
  assert jax.tree.structure(relayout_layers(opt_state, scan=False)) == jax.tree.structure(
      optax.adam(1e-3).init(p_unrolled))
  mesh = jax.make_mesh((1,), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
  abstract = jax.tree.map(lambda v: jax.ShapeDtypeStruct(v.shape, v.dtype, sharding=NamedSharding(
      mesh, PartitionSpec(*(None,) * v.ndim))), p_unrolled)
  stacked = relayout_layers(abstract, scan=True)["params"]["blocks"]["layers"]["spatial"]["mlp"]
  assert stacked["fc1"]["kernel"].shape == (model.depth // 2,) + abstract["params"]["blocks"][
      "layer_0"]["spatial"]["mlp"]["fc1"]["kernel"].shape
  assert stacked["fc1"]["kernel"].sharding.spec == PartitionSpec(None, None, None)
  with pytest.raises(ValueError, match="cannot stack layers"):
    relayout_layers({"blocks": {"layer_0": {}, "layer_2": {}}}, scan=True)


@pytest.mark.slow
def test_remat_policies_change_nothing_but_the_memory_the_backward_pass_keeps():
  """Every remat policy gives the loss and gradient of no remat; what each keeps shows in the
  compiled gradient's temporaries: none > dots_elementwise (the named normed inputs and GELU
  outputs) > dots_attention (the named attention outputs) > dots > full (dots_all keeps every
  matmul, attention's too, so it sits beside dots_attention, unordered). One compile a policy."""
  x, t, a = _inputs(4, 8, 16, 16, 4, 7)
  plain = STDiT(in_channels=4, patch_size=2, depth=4, hidden_size=64, num_heads=4, num_frames=8,
                action_dim=7, cond="per_frame", remat="none")
  params = perturbed(jax.jit(plain.init)(jax.random.key(0), x, t, a), jax.random.key(1))
  temp, results = {}, {}
  for policy in ("none", "dots_elementwise", "dots_attention", "dots", "full", "dots_all"):
    model = plain.clone(remat=policy)
    loss = jax.value_and_grad(lambda p: jnp.mean(model.apply(p, x, t, a) ** 2))
    compiled = jax.jit(loss).lower(params).compile()
    temp[policy] = compiled.memory_analysis().temp_size_in_bytes
    results[policy] = compiled(params)
  ordered = [temp[p] for p in ("none", "dots_elementwise", "dots_attention", "dots", "full")]
  assert ordered == sorted(ordered, reverse=True) and len(set(ordered)) == len(ordered), temp
  (value, grads) = results.pop("none")
  for policy, (v, g) in results.items():
    np.testing.assert_allclose(v, value, rtol=1e-6, err_msg=policy)
    for u, w in zip(jax.tree.leaves(g), jax.tree.leaves(grads)):
      np.testing.assert_allclose(u, w, rtol=1e-5, atol=1e-6, err_msg=policy)
  with pytest.raises(ValueError, match="remat must be one of"):
    plain.clone(remat="some").apply(params, x, t, a)


@pytest.mark.slow
def test_bf16_compute_keeps_float32_params():
  model, params, (x, t, a) = _model("frame")
  bf16 = model.clone(dtype="bfloat16")
  assert all(v.dtype == jnp.float32
             for v in jax.tree.leaves(jax.eval_shape(bf16.init, jax.random.key(0), x, t, a)))
  ref, out = jit_apply(model)(params, x, t, a), jit_apply(bf16)(params, x, t, a)
  assert out.dtype == jnp.float32 and bool(jnp.isfinite(out).all())
  assert float(jnp.abs(out - ref).max()) < 0.1 * float(jnp.abs(ref).max()) + 1e-3


@pytest.mark.parametrize("fields", [dict(temporal_pos="rope"), dict(spatial_pos="rope"),
                                    dict(temporal_pos="rope", spatial_pos="rope")])
def test_rope_positions_run(fields):
  model, params, (x, t, a) = _model("frame", **fields)
  out = jit_apply(model)(params, x, t, a)
  assert out.shape == x.shape and bool(jnp.isfinite(out).all())


@pytest.mark.slow
def test_sincos_plus_rope_is_both_positions():
  """The position schemes have no parameters: one set of weights runs under each, and
  'sincos+rope' gives neither the sin-cos-only nor the RoPE-only output."""
  outs = {}
  for pos in ("sincos", "rope", "sincos+rope"):
    model, params, (x, t, a) = _model("frame", spatial_pos=pos)
    outs[pos] = jit_apply(model)(params, x, t, a)
  for other in ("sincos", "rope"):
    assert float(jnp.abs(outs["sincos+rope"] - outs[other]).max()) > 1e-3
  with pytest.raises(ValueError, match="spatial_pos must be one of"):
    _model("frame", spatial_pos="rope+sincos")


def test_axial_rope_scores_depend_only_on_the_2d_offset():
  q, k = jax.random.normal(jax.random.key(0), (2, 1, 6, 2, 8))
  grid = jnp.asarray([[0, 0], [0, 3], [2, 1], [4, 4], [1, 5], [3, 0]])

  def scores(positions):
    return jnp.einsum("nqhd,nkhd->nhqk", layers.rope(q, positions), layers.rope(k, positions))

  np.testing.assert_allclose(scores(grid + jnp.asarray([5, -2])), scores(grid), atol=1e-4)
  # a shift along one axis only is still a shift: the two axes are rotated separately
  moved = scores(grid.at[:, 1].add(jnp.arange(6)))
  assert float(jnp.abs(moved - scores(grid)).max()) > 1e-2
  with pytest.raises(ValueError, match="divisible by 4"):
    layers.rope(q[..., :6], grid)


def test_fourier_action_features_are_the_action_and_its_sines_and_cosines():
  a = jnp.array([[0.25, -1.0]])
  encoded = layers.fourier_encode(a, 2)  # [a0, a1, sin(pi a), sin(2 pi a), cos(pi a), cos(2 pi a)]
  angles = np.pi * np.array([0.25, -1.0, 0.5, -2.0])
  np.testing.assert_allclose(encoded[0], np.concatenate([[0.25, -1.0], np.sin(angles),
                                                         np.cos(angles)]), atol=1e-6)
  embedder = layers.ActionEmbedder(8, fourier_features=2)
  params = embedder.init(jax.random.key(0), a)
  assert nn.unbox(params)["params"]["proj"]["kernel"].shape == (2 * (1 + 2 * 2), 8)
  with pytest.raises(ValueError, match="action_fourier_features must be >= 0, got -1"):
    STDiT(depth=2, hidden_size=32, num_heads=2, action_fourier_features=-1).init(
        jax.random.key(0), *_inputs(1, 2, 8, 8, 4, 7))


@pytest.mark.parametrize("cond,fourier", [("frame", 0), ("video", 0), ("per_frame", 0),
                                          ("per_frame", 3)])
@pytest.mark.slow
def test_flop_counter_matches_xla(cond, fourier):
  model = STDiT(in_channels=4, patch_size=2, depth=4, hidden_size=256, num_heads=4,
                num_frames=8, action_dim=7, cond=cond, action_fourier_features=fourier,
                scan_layers=False)  # XLA counts a loop body once
  x, t, a = _inputs(2, 8, 16, 16, 4, 7)
  params = jax.jit(model.init)(jax.random.key(0), x, t, a)
  cost = jax.jit(model.apply).lower(params, x, t, a).compile().cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else cost
  analytic = forward_flops(model, 2, 8, 16, 16)
  assert abs(analytic / cost["flops"] - 1) < 0.05, (analytic, cost["flops"])


def test_flops_of_irasim_xl_match_the_design_figure():
  config = load_config(str(ROOT / "configs" / "irasim.py:XL"))
  flops = forward_flops(STDiT(**config.model), 1, 16, 32, 40)
  assert 4.6e12 < flops < 4.9e12  # docs/design.md: about 4.75 TFLOP


def test_action_place_tells_each_patch_where_the_action_points():
  from wmjax.nn.layers import PlaceEmbedder
  embed = PlaceEmbedder(8, widths=(0.1,))
  # at the initial scale 0.5: image coordinates (column 0.25, row -0.75), the centre of patch
  # (row 0, column 2) of a 4x4 grid, whose centres lie at -0.75, -0.25, 0.25, 0.75
  place = jnp.asarray([[[0.5, -1.5]]])  # [B=1, m=1, 2]
  params = embed.init(jax.random.key(0), place, 4, 4)
  params["params"]["proj"]["kernel"] = jnp.zeros((3, 8)).at[2, 0].set(1.0).at[0, 1].set(1.0)
  out = embed.apply(params, place, 4, 4)[0, 0]  # [P, D]
  bump, column_offset = out[:, 0].reshape(4, 4), out[:, 1].reshape(4, 4)
  assert int(jnp.argmax(bump)) == 2 and float(bump[0, 2]) == pytest.approx(1.0)
  assert float(bump[3, 0]) < 1e-6  # far patches do not see it
  np.testing.assert_allclose(column_offset[1], [-1.0, -0.5, 0.0, 0.5], atol=1e-6)


def test_action_place_is_silent_where_actions_are_dropped_and_checked():
  model, params, (x, t, a) = _model("per_frame", action_place=(0, 1))
  drop = jnp.ones((x.shape[0],), bool)
  apply = jit_apply(model)
  np.testing.assert_allclose(apply(params, x, t, a, None, drop),
                             apply(params, x, t, a.at[..., :2].add(3.0), None, drop), atol=1e-6)
  assert float(jnp.abs(apply(params, x, t, a) - apply(params, x, t, a.at[..., 1].add(3.0))).max()
               ) > 1e-3
  for place in [(0,), (1, 1), (0, 7)]:
    with pytest.raises(ValueError, match="action_place must be \\(\\) or two different"):
      _model("per_frame", action_place=place)
  with pytest.raises(ValueError, match="so cond must be 'frame' or 'per_frame', got 'video'"):
    _model("video", action_place=(0, 1))


def test_views_share_positions_and_only_the_view_embedding_tells_them_apart():
  """model.views=2: the views of a frame are exchangeable but for the view embedding (same 2-D
  positions, one spatial attention over all their tokens); views=1 on the same frame is the
  tiled baseline, whose positions run over the whole canvas."""
  model, params, (x, t, a) = _model("per_frame", views=2, spatial_pos="sincos+rope")
  params = nn.meta.unbox(params)
  swap = lambda v: jnp.concatenate([v[..., 4:, :], v[..., :4, :]], axis=-2)  # 8 wide: 2 views of 4
  forward = jit_apply(model)
  apply = lambda p, frames: forward(p, frames, t, a)
  assert params["params"]["view_embed"].shape == (2, model.hidden_size)
  blind = jax.tree_util.tree_map_with_path(
      lambda path, v: jnp.zeros_like(v) if "view_embed" in jax.tree_util.keystr(path) else v,
      params)
  np.testing.assert_allclose(apply(blind, swap(x)), swap(apply(blind, x)), rtol=1e-4, atol=1e-5)
  assert not np.allclose(apply(params, swap(x)), swap(apply(params, x)), atol=1e-3)
  tiled = model.clone(views=1)
  no_view = {"params": {k: v for k, v in blind["params"].items() if k != "view_embed"}}
  assert not np.allclose(jit_apply(tiled)(no_view, x, t, a), apply(blind, x), atol=1e-3)
  with pytest.raises(ValueError, match="must hold 2 views of whole 2-pixel patches"):
    apply(params, x[..., :6, :])


@pytest.mark.parametrize("shape_change,message", [
    (dict(c=3), "must have 4 channels, got 3"),
    (dict(h=9), "divisible by the patch size 2, got 9x8"),
    (dict(t=9), "supports at most 8 frames, got 9"),
    (dict(a=6), r"actions must be \[B, T-1, A\] = \(2, 5, 7\)"),
])
def test_bad_shapes_raise_clear_errors(shape_change, message):
  model, params, _ = _model("frame")
  dims = dict(b=2, t=6, h=8, w=8, c=4, a=7)
  dims.update(shape_change)
  x, t, a = _inputs(**dims)
  with pytest.raises(ValueError, match=message):
    jit_apply(model)(params, x, t, a)


def test_world_model_from_config_rejects_mismatched_sampler():
  config = tiny_config("irasim.py:S", "sampling.sampler='euler'")
  with pytest.raises(ValueError, match="does not fit"):
    WorldModel.from_config(config)


# --------------------------------------------------------------------------- temporal KV cache


def _cached_output(model, params, x, t, a, c, mask=None, drop=None):
  apply = jit_apply(model)
  cache = apply(params, x[:, :c], t[:, :c], a, mask, drop, method="encode_context")
  return apply(params, cache, x[:, c:], t[:, c:], a, mask, drop, method="extend")


@pytest.mark.parametrize("cond,fields,c", [
    ("frame", {}, 1),
    ("frame", dict(trajectory_in_temporal=True, temporal_pos="rope"), 4),
    ("video", dict(scan_layers=False), 2),
    ("per_frame", dict(temporal_pos="rope", scan_layers=False), 1),
    ("per_frame", {}, 3),
    # temporal-first blocks, each with positions or an action embedding of its own
    ("per_frame", dict(temporal_first=True, spatial_pos="rope", temporal_pos="rope"), 2),
    ("per_frame", dict(temporal_first=True, spatial_pos="sincos+rope", action_place=(0, 1)), 2),
])
@pytest.mark.slow
def test_extend_after_the_cached_context_equals_the_whole_window(cond, fields, c):
  model, params, (x, t, a) = _model(cond, **fields)
  mask = jnp.asarray([[True] * 5, [True, False, True, True, False]])
  drop = jnp.asarray([False, True])
  whole = jit_apply(model)(params, x, t, a, mask, drop)
  got = _cached_output(model, params, x, t, a, c, mask, drop)
  assert got.shape == x[:, c:].shape
  np.testing.assert_allclose(got, whole[:, c:], rtol=1e-5, atol=1e-5)
  # The cached context really is the context: other context frames give another output.
  other = _cached_output(model, params, x.at[:, :c].multiply(-1.0), t, a, c, mask, drop)
  assert float(jnp.abs(other - got).max()) > 1e-3


def test_kv_cache_needs_causal_temporal_attention():
  model, params, (x, t, a) = _model("frame", causal_temporal=False)
  with pytest.raises(ValueError, match="needs model.causal_temporal=True"):
    jit_apply(model)(params, x[:, :2], t[:, :2], a, method="encode_context")
  config = tiny_config("irasim.py:S", "sampling.kv_cache=True")
  with pytest.raises(ValueError, match="sampling.kv_cache=True needs model.causal_temporal=True"):
    WorldModel.from_config(config)


def test_kv_cache_inputs_are_checked():
  model, params, (x, t, a) = _model("frame")
  with pytest.raises(ValueError, match="must leave frames to generate in the window of 6"):
    jit_apply(model)(params, x, t, a, method="encode_context")
  cache = jit_apply(model)(params, x[:, :2], t[:, :2], a, method="encode_context")
  assert [k.shape for k in cache] == [(1, 2 * 16, 2, 2, 16)] * 2  # [layers, B*P, c, H, d]
  with pytest.raises(ValueError, match=r"a cache of 2 frames and 3 new frames make 5, but the "
                                       r"actions describe a window of 6"):
    jit_apply(model)(params, cache, x[:, 3:], t[:, 3:], a, method="extend")
  with pytest.raises(ValueError, match=r"\[layers, B\*P, c, heads, head_dim\] = \(1, 32, 2, 2, 16\)"):
    jit_apply(model)(params, jax.tree.map(lambda k: k[:, :16], cache), x[:, 2:], t[:, 2:], a,
                     method="extend")


@pytest.mark.slow
def test_sampling_flops_count_a_cached_context_once(capsys):
  from wmjax import cli
  from wmjax.rollout import block_flops
  config = ROOT / "configs" / "wpe_600m.py"
  cached = WorldModel.from_config(tiny_config("wpe_600m.py", "sampling.num_steps=4"))
  uncached = WorldModel.from_config(tiny_config("wpe_600m.py", "sampling.num_steps=4",
                                                "sampling.kv_cache=False"))
  f = lambda frames: forward_flops(cached.network, 2, frames, 8, 8)
  assert cached.sampler.kv_cache
  assert block_flops(uncached, 2, 3, 5, 8, 8) == 4 * f(8)
  assert block_flops(cached, 2, 3, 5, 8, 8) == f(3) + 4 * f(5)
  reports = []
  for kv in ("True", "False"):
    assert cli.main(["info", "--config", str(config), f"--config.sampling.kv_cache={kv}"]) == 0
    reports.append(json.loads(capsys.readouterr().out))
  assert reports[0]["kv_cache"] and not reports[1]["kv_cache"]
  assert reports[0]["gflop_per_generated_frame"] < 0.6 * reports[1]["gflop_per_generated_frame"]


@pytest.mark.slow
def test_temporal_first_changes_the_block_order_not_the_parameters():
  model, params, (x, t, a) = _model("per_frame")
  reordered = model.clone(temporal_first=True)
  assert (jax.tree.map(jnp.shape, jax.eval_shape(reordered.init, jax.random.key(0), x, t, a))
          == jax.tree.map(jnp.shape, params))
  assert float(jnp.abs(jit_apply(reordered)(params, x, t, a)
                       - jit_apply(model)(params, x, t, a)).max()) > 1e-4
