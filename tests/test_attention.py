"""Attention backends: XLA against a plain softmax, splash (Pallas interpret mode on CPU) and the
cuDNN path's padding against XLA, backend choice and its errors, and whole models per backend."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import jit_apply, tiny_world_model
from wmjax.nn import attention
from wmjax.nn.attention import attend, prefix_causal_mask, resolve_backend

pytestmark = pytest.mark.unit

ON_GPU = jax.default_backend() == "gpu"


def _qkv(lq, lk, heads=2, head_dim=16, batch=2, dtype=jnp.float32, seed=0):
  kq, kk, kv = jax.random.split(jax.random.key(seed), 3)
  q = jax.random.normal(kq, (batch, lq, heads, head_dim), dtype)
  k = jax.random.normal(kk, (batch, lk, heads, head_dim), dtype)
  v = jax.random.normal(kv, (batch, lk, heads, head_dim), dtype)
  return q, k, v


def _reference(q, k, v, causal):
  """Softmax attention in float64 numpy; queries are the last Lq of the Lk positions."""
  q, k, v = (np.asarray(a, np.float64) for a in (q, k, v))
  logits = np.einsum("nqhd,nkhd->nhqk", q, k) / np.sqrt(q.shape[-1])
  if causal:
    logits = np.where(prefix_causal_mask(q.shape[1], k.shape[1]), logits, -np.inf)
  weights = np.exp(logits - logits.max(-1, keepdims=True))
  weights /= weights.sum(-1, keepdims=True)
  return np.einsum("nhqk,nkhd->nqhd", weights, v)


def test_prefix_causal_mask_lets_queries_see_the_whole_prefix():
  mask = prefix_causal_mask(2, 5)
  np.testing.assert_array_equal(mask, [[1, 1, 1, 1, 0], [1, 1, 1, 1, 1]])
  np.testing.assert_array_equal(prefix_causal_mask(3, 3), np.tril(np.ones((3, 3), bool)))


@pytest.mark.parametrize("lq,lk,causal", [(7, 7, False), (7, 7, True), (3, 8, True), (3, 8, False)])
def test_xla_matches_plain_softmax(lq, lk, causal):
  q, k, v = _qkv(lq, lk)
  np.testing.assert_allclose(attend(q, k, v, causal=causal, backend="xla"),
                             _reference(q, k, v, causal), atol=1e-5)


@pytest.mark.parametrize("lq,lk,causal", [
    (200, 200, True),   # padded to two 128-token blocks
    (256, 256, False),  # whole blocks
    (130, 300, True),   # queries after a 170-token prefix
    (16, 16, True),     # shorter than a block: the XLA route
])
def test_splash_equals_xla(lq, lk, causal):
  q, k, v = _qkv(lq, lk)
  np.testing.assert_allclose(attend(q, k, v, causal=causal, backend="splash"),
                             attend(q, k, v, causal=causal, backend="xla"), atol=2e-5)


@pytest.mark.slow
def test_splash_equals_xla_in_bfloat16_and_in_gradients():
  q, k, v = _qkv(200, 200, dtype=jnp.bfloat16)
  got = attend(q, k, v, causal=True, backend="splash")
  assert got.dtype == jnp.bfloat16
  np.testing.assert_allclose(got.astype(jnp.float32),
                             attend(q, k, v, causal=True, backend="xla").astype(jnp.float32),
                             atol=2e-2)
  q, k, v = _qkv(200, 200)

  def grads(backend):
    loss = lambda q, k, v: jnp.sum(attend(q, k, v, causal=True, backend=backend) ** 2)
    return jax.grad(loss, argnums=(0, 1, 2))(q, k, v)

  for got, want in zip(grads("splash"), grads("xla")):
    np.testing.assert_allclose(got, want, atol=5e-5)


def test_cudnn_route_pads_the_head_dimension_and_keeps_the_scale(monkeypatch):
  """The padding of the cuDNN route (head dim 12 -> 16, scale 1/sqrt(12)) run through XLA: on a
  machine without a GPU only the kernel call is swapped."""
  calls = []
  xla_attention = jax.nn.dot_product_attention

  def recording(q, k, v, *args, implementation=None, **kwargs):
    calls.append((q.shape[-1], implementation))
    return xla_attention(q, k, v, *args, implementation="xla", **kwargs)

  monkeypatch.setattr(attention.jax.nn, "dot_product_attention", recording)
  for lq, lk in [(6, 6), (2, 6)]:
    q, k, v = _qkv(lq, lk, head_dim=12)
    out = attention._cudnn(q, k, v, causal=True)
    assert out.shape == q.shape
    np.testing.assert_allclose(out, _reference(q, k, v, True), atol=1e-5)
  assert calls == [(16, "cudnn"), (16, "cudnn")]


def test_cudnn_backend_sends_short_sequences_to_xla(monkeypatch):
  """Under ``cudnn`` the temporal axis (fewer keys than FLASH_MIN_KEYS) goes through XLA, the
  spatial axis through the flash kernel."""
  flash_lengths = []
  monkeypatch.setattr(attention, "resolve_backend", lambda name, dtype: "cudnn")
  monkeypatch.setattr(attention, "_cudnn",
                      lambda q, k, v, causal: flash_lengths.append(k.shape[1]) or q)
  short, long = 16, attention.FLASH_MIN_KEYS
  q, k, v = _qkv(short, short, head_dim=8)
  np.testing.assert_allclose(attend(q, k, v, causal=True, backend="cudnn"),
                             _reference(q, k, v, True), atol=1e-5)
  q, k, v = _qkv(long, long, head_dim=8)
  attend(q, k, v, backend="cudnn")
  assert flash_lengths == [long]


@pytest.mark.skipif(not ON_GPU, reason="cuDNN flash attention needs a GPU")
@pytest.mark.parametrize("lq,lk,head_dim", [(256, 256, 64), (15, 16, 72)])
def test_cudnn_equals_xla_in_bfloat16(lq, lk, head_dim):
  q, k, v = _qkv(lq, lk, head_dim=head_dim, dtype=jnp.bfloat16)
  got = attend(q, k, v, causal=True, backend="cudnn").astype(jnp.float32)
  np.testing.assert_allclose(got, _reference(q, k, v, True), atol=2e-2)


def test_backend_choice():
  assert resolve_backend("auto", jnp.bfloat16, "gpu") == "cudnn"
  assert resolve_backend("auto", jnp.float32, "gpu") == "xla"
  assert resolve_backend("auto", jnp.float32, "tpu") == "splash"
  assert resolve_backend("auto", jnp.bfloat16, "cpu") == "xla"
  assert resolve_backend(None, jnp.float32, "gpu") == "xla"
  assert resolve_backend("splash", jnp.float32, "cpu") == "splash"  # interpret mode


@pytest.mark.parametrize("backend,dtype,platform,message", [
    ("flash", jnp.bfloat16, "gpu", r"attention_impl must be one of .*got 'flash'"),
    ("cudnn", jnp.float32, "gpu", r"computes in bfloat16 or float16.*got float32"),
    ("cudnn", jnp.bfloat16, "cpu", r"'cudnn' needs a GPU, but JAX runs on 'cpu'"),
])
def test_backend_errors_say_what_was_expected(backend, dtype, platform, message):
  with pytest.raises(ValueError, match=message):
    resolve_backend(backend, dtype, platform)


@pytest.mark.parametrize("backend,lq,lk,causal", [
    ("xla", 7, 7, True), ("xla", 3, 8, True), ("xla", 5, 5, False),
    ("splash", 130, 200, True),  # flash kernels fold the batch axes into N
])
def test_batch_axes_before_the_heads_equal_sequences_folded_into_n(backend, lq, lk, causal):
  """``q [N, L, M, H, d]`` (temporal attention over ``[B, T, P, ...]`` tokens) attends as the
  ``N*M`` sequences of ``[N*M, L, H, d]`` do, in float32 and bfloat16."""
  for dtype, atol in ((jnp.float32, 2e-5), (jnp.bfloat16, 1e-2)):
    q, k, v = _qkv(lq * 3, lk * 3, batch=1, dtype=dtype)
    split = lambda a: a.reshape(1, 3, a.shape[1] // 3, 2, 16).transpose(0, 2, 1, 3, 4)
    fold = lambda a: a.transpose(0, 2, 1, 3, 4).reshape(3, a.shape[1], 2, 16)
    got = attend(split(q), split(k), split(v), causal=causal, backend=backend)
    want = attend(fold(split(q)), fold(split(k)), fold(split(v)), causal=causal, backend=backend)
    assert got.shape == (1, lq, 3, 2, 16)
    np.testing.assert_allclose(fold(got).astype(jnp.float32), want.astype(jnp.float32), atol=atol)


def test_attention_rejects_mismatched_shapes():
  q, k, v = _qkv(4, 4)
  with pytest.raises(ValueError, match=r"q \[N, Lq, ..., H, d\] and k, v \[N, Lk, ..., H, d\]"):
    attend(q, k[..., :8], v)
  with pytest.raises(ValueError, match=r"at least as many keys as queries, got Lq=4 > Lk=2"):
    attend(q, k[:, :2], v[:, :2])


def test_model_config_rejects_cudnn_in_float32():
  with pytest.raises(ValueError, match=r"set model.dtype='bfloat16'"):
    tiny_world_model("wpe_600m.py", "model.attention_impl='cudnn'", frame_shape=(8, 8, 16))


@pytest.mark.parametrize("config,channels", [("irasim.py:S", 4), ("wpe_600m.py", 16)])
def test_whole_model_with_splash_equals_xla(config, channels, monkeypatch):
  """A 32x32 frame of 2x2 patches is a 256-token spatial sequence: the splash kernel runs in the
  spatial blocks, XLA in the short temporal ones; same parameters, same output."""
  lengths = []
  splash_kernel = attention._splash
  monkeypatch.setattr(attention, "_splash",
                      lambda q, *args: lengths.append(q.shape[1]) or splash_kernel(q, *args))
  wm, params = tiny_world_model(config, frame_shape=(32, 32, channels))
  splash, _ = tiny_world_model(config, "model.attention_impl='splash'", frame_shape=(8, 8, channels))
  x = jax.random.normal(jax.random.key(1), (1, 3, 32, 32, channels))
  t = jnp.asarray([[0.0, 400.0, 800.0]])
  actions = jax.random.normal(jax.random.key(2), (1, 2, wm.network.action_dim))
  want = jit_apply(wm.network)(params, x, t, actions)
  got = jit_apply(splash.network)(params, x, t, actions)
  assert lengths and set(lengths) == {256}
  assert float(jnp.abs(want).mean()) > 0
  np.testing.assert_allclose(got, want, atol=1e-4, rtol=1e-4)


def test_splash_runs_one_kernel_per_device_under_a_mesh(monkeypatch):
  """XLA cannot partition a Pallas call: under a mesh context the sequences are split over the
  batch axes and the heads over 'tensor' with shard_map, and the result is unchanged."""
  assert jax.device_count() == 8
  local_shapes = []
  local = attention._splash_local
  monkeypatch.setattr(attention, "_splash_local",
                      lambda q, *args, **kw: local_shapes.append(q.shape) or local(q, *args, **kw))
  q, k, v = _qkv(200, 200, heads=2, batch=8)
  want = attend(q, k, v, causal=True, backend="xla")
  mesh = jax.make_mesh((4, 1, 2), ("data", "fsdp", "tensor"),
                       axis_types=(jax.sharding.AxisType.Auto,) * 3)
  with jax.set_mesh(mesh):
    got = jax.jit(lambda q, k, v: attend(q, k, v, causal=True, backend="splash"))(q, k, v)
  assert local_shapes == [(2, 200, 1, 16)]  # 8 sequences / 4, 2 heads / 2
  np.testing.assert_allclose(got, want, atol=2e-5)
