"""Actions written as digit tokens (the WPE figure-3 text encoding) and the ST-DiT reading them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import jit_apply, perturbed, tiny_config
from wmjax.nn import STDiT
from wmjax.nn.text_actions import MINUS, PLUS, POINT, SEPARATOR, action_tokens

pytestmark = pytest.mark.unit


def test_numbers_become_sign_digits_point_separator():
  got = np.asarray(action_tokens(jnp.asarray([[1.25, -0.4], [12.0, -0.004]])))
  np.testing.assert_array_equal(got, [
      [PLUS, 1, POINT, 2, 5, SEPARATOR, MINUS, 0, POINT, 4, 0, SEPARATOR],
      # 12 is clipped to the largest writable number; -0.004 rounds to -0.00
      [PLUS, 9, POINT, 9, 9, SEPARATOR, MINUS, 0, POINT, 0, 0, SEPARATOR]])
  assert action_tokens(jnp.zeros((3, 5, 4)), int_digits=2, frac_digits=1).shape == (3, 5, 24)


def _text_model(cond="per_frame"):
  config = tiny_config("irasim.py:S", f"model.cond={cond!r}", "model.causal_temporal=True")
  model = STDiT(**{**dict(config.model), "action_encoding": "text"})
  k = jax.random.split(jax.random.key(0), 3)
  x, t, a = (jax.random.normal(k[0], (2, 4, 8, 8, 4)), jax.random.uniform(k[1], (2, 4)) * 999,
             jax.random.normal(k[2], (2, 3, 7)))
  params = perturbed(jax.jit(model.init)(jax.random.key(0), x, t, a), jax.random.key(1))
  return model, params, (x, t, a)


@pytest.mark.slow
def test_text_encoded_actions_condition_their_frame():
  model, params, (x, t, a) = _text_model()
  apply = jit_apply(model)
  base = apply(params, x, t, a)
  moved = apply(params, x, t, a.at[:, 1].add(0.5))  # action 1 moves frame 1 to frame 2
  diff = jnp.abs(moved - base).reshape(2, 4, -1).max(-1)
  assert float(diff[:, :2].max()) == 0.0 and float(diff[:, 2].min()) > 1e-4
  # a change below the written precision is invisible to the text encoding
  same = apply(params, x, t, jnp.round(a * 100) / 100 + 1e-4)
  np.testing.assert_allclose(same, apply(params, x, t, jnp.round(a * 100) / 100), atol=1e-6)


def test_text_encoding_needs_one_action_per_frame():
  with pytest.raises(ValueError, match="cond must be 'frame' or 'per_frame'"):
    _text_model("video")
