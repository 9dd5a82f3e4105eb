"""The fused MLP kernels (wmjax.nn.kernels.mlp) against plain JAX, in Pallas interpret mode."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import perturbed, tiny_config
from wmjax.nn import STDiT, kernels
from wmjax.nn.kernels import mlp as fused

pytestmark = pytest.mark.unit

SMALL = fused.Blocks(rows=32, cols=64, depth=16)


def _weights(k=32, n=128, f=48, seed=0):
  keys = jax.random.split(jax.random.key(seed), 4)
  return (jax.random.normal(keys[0], (k, n)) * 0.2, jax.random.normal(keys[1], (n,)) * 0.1,
          jax.random.normal(keys[2], (n, f)) * 0.1, jax.random.normal(keys[3], (f,)) * 0.1)


def test_gelu_and_its_derivative_are_jax_tanh_gelu():
  z = jnp.linspace(-6.0, 6.0, 101)
  np.testing.assert_allclose(fused.gelu(z), jax.nn.gelu(z, approximate=True), atol=2e-5)
  want = jax.vmap(jax.grad(lambda v: jax.nn.gelu(v, approximate=True)))(z)
  np.testing.assert_allclose(fused.gelu_derivative(z), want, atol=2e-5)


def test_kernels_equal_their_definitions_with_padded_rows():
  """150 rows in 32-row tiles: the last tile is padded, and the padding does not leak."""
  w1, b1, w2, _ = _weights()
  x = jax.random.normal(jax.random.key(1), (150, 32))
  pre, act = fused.dense_gelu(x, w1, b1, SMALL, interpret=True)
  np.testing.assert_allclose(pre, x @ w1 + b1, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(act, jax.nn.gelu(x @ w1 + b1, approximate=True), rtol=1e-5, atol=1e-5)
  (act_only,) = fused.dense_gelu(x, w1, b1, SMALL, interpret=True, keep_pre=False)
  np.testing.assert_array_equal(act_only, act)
  g = jax.random.normal(jax.random.key(2), (150, 48))
  dpre, act2 = fused.dense_gelu_backward(g, w2, pre, SMALL, interpret=True)
  np.testing.assert_allclose(dpre, (g @ w2.T) * fused.gelu_derivative(pre), rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(act2, act, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("dtype,tol", [(jnp.float32, 2e-5), (jnp.bfloat16, 3e-2)])
def test_fused_mlp_value_and_gradients_match_plain_jax(dtype, tol):
  w1, b1, w2, b2 = _weights()
  x = jax.random.normal(jax.random.key(3), (3, 50, 32)).astype(dtype)
  probe = jnp.cos(jnp.arange(48.0))

  def loss(impl):
    return lambda *a: (fused.mlp(*a, impl=impl, blocks=SMALL, interpret=True).astype(jnp.float32)
                       * probe).sum()

  # the truth in float32 on the same (rounded) inputs
  want, want_grads = jax.value_and_grad(loss("xla"), argnums=range(5))(
      x.astype(jnp.float32), w1, b1, w2, b2)
  got, got_grads = jax.value_and_grad(loss("pallas"), argnums=range(5))(x, w1, b1, w2, b2)
  np.testing.assert_allclose(got, want, rtol=tol)
  assert got_grads[0].dtype == dtype
  for name, g, w in zip(["x", "w1", "b1", "w2", "b2"], got_grads, want_grads):
    scale = float(jnp.abs(w.astype(jnp.float32)).max())
    np.testing.assert_allclose(np.asarray(g, np.float32) / scale, np.asarray(w, np.float32) / scale,
                               atol=tol, err_msg=name)


def test_remat_keeps_the_fused_pre_activation_under_dots():
  """The 'dots' policy saves the named pre-activation: after XLA's dead-code elimination the
  compiled step runs as many kernel loops as without remat (the forward kernel is not run again
  in the backward pass); 'full' runs more."""
  from wmjax.nn.dit import REMAT_POLICIES
  w1, b1, w2, b2 = _weights(f=32)
  x = jax.random.normal(jax.random.key(4), (64, 32))

  def kernel_loops(policy):
    mlp = lambda x: fused.mlp(x, w1, b1, w2, b2, blocks=SMALL, interpret=True)
    layer = mlp if policy is None else jax.checkpoint(mlp, policy=REMAT_POLICIES[policy])
    step = jax.jit(jax.value_and_grad(lambda x: jnp.sin(layer(layer(x))).sum()))
    return step.lower(x).compile().as_text().count(" while(")  # interpret mode: loops

  plain = kernel_loops(None)
  assert kernel_loops("dots") == plain
  assert kernel_loops("full") > plain


@pytest.mark.slow
def test_model_with_the_fused_kernels_equals_the_xla_model():
  """The ST-DiT with both fused kernels, the MLP's and the LayerNorm's (test_norm_kernel.py), and
  remat 'dots': the same parameters, outputs and gradients as with XLA's ops (one model for both
  kernels: in interpret mode each model compiles for long); 'auto' is 'xla' off a GPU."""
  model = STDiT(**tiny_config("irasim.py:S").model)
  fused_model = model.clone(mlp_kernel="pallas", norm_kernel="pallas")
  k = jax.random.split(jax.random.key(0), 4)
  x = jax.random.normal(k[0], (2, 2, 4, 4, 4))
  t = jax.random.uniform(k[1], (2, 2), maxval=999.0)
  a = jax.random.normal(k[2], (2, 1, 7))
  # the parameter tree does not depend on the kernel choice
  shapes = jax.eval_shape(model.init, k[3], x, t, a)
  assert jax.eval_shape(fused_model.init, k[3], x, t, a) == shapes
  # random parameters everywhere (no zero-initialised adaLN), without compiling an init
  params = perturbed(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), k[3])
  probe = jax.random.normal(jax.random.key(2), x.shape)
  loss = lambda m: jax.jit(jax.value_and_grad(lambda p: jnp.mean(m.apply(p, x, t, a) * probe)))
  got, got_grads = loss(fused_model.clone(remat="dots"))(params)
  want, want_grads = loss(model)(params)
  np.testing.assert_allclose(got, want, rtol=1e-5)
  for u, v in zip(jax.tree.leaves(got_grads), jax.tree.leaves(want_grads)):
    np.testing.assert_allclose(u, v, rtol=1e-4, atol=1e-6)
  assert kernels.resolve_kernel("model.mlp_kernel", "auto") == "xla"
  assert kernels.resolve_kernel("model.mlp_kernel", "auto", platform="gpu") == "pallas"
  with pytest.raises(ValueError, match="mlp_kernel must be one of"):
    model.clone(mlp_kernel="triton").apply(params, x, t, a)


def test_fused_mlp_runs_one_kernel_per_device_under_a_mesh(monkeypatch):
  """Rows are split over the batch axes and the hidden width over 'tensor'; result unchanged."""
  assert jax.device_count() == 8
  shapes = []
  local = fused._dense_gelu_local
  monkeypatch.setattr(fused, "_dense_gelu_local",
                      lambda x, *a, **kw: shapes.append(x.shape) or local(x, *a, **kw))
  w1, b1, w2, b2 = _weights()
  x = jax.random.normal(jax.random.key(5), (8, 16, 32))
  loss = lambda impl: (lambda *p: (fused.mlp(*p, impl=impl, blocks=SMALL, interpret=True) ** 2).sum())
  want = jax.grad(loss("xla"), argnums=range(5))(x, w1, b1, w2, b2)
  mesh = jax.make_mesh((4, 1, 2), ("data", "fsdp", "tensor"),
                       axis_types=(jax.sharding.AxisType.Auto,) * 3)
  with jax.set_mesh(mesh):
    got = jax.jit(jax.grad(loss("pallas"), argnums=range(5)))(x, w1, b1, w2, b2)
  assert shapes == [(32, 32)]  # 128 rows / 4; the hidden width 128 / 2 is in w1's local block
  for g, w in zip(got, want):
    np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-5)


def test_bad_shapes_and_untileable_widths_are_clear_errors():
  w1, b1, w2, b2 = _weights()
  with pytest.raises(ValueError, match=r"x \[..., K\], w1 \[K, N\]"):
    fused.mlp(jnp.ones((4, 31)), w1, b1, w2, b2)
  w1, b1, w2, b2 = _weights(k=24, n=40, f=24)
  x = jnp.ones((4, 24))
  with pytest.raises(ValueError, match="multiples of 16"):
    fused.mlp(x, w1, b1, w2, b2, impl="pallas")
  np.testing.assert_allclose(fused.mlp(x, w1, b1, w2, b2, impl="auto"),
                             fused.mlp_reference(x, w1, b1, w2, b2), rtol=1e-6)
