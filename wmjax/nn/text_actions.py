"""Actions as text: the WPE study (figure 3) of raw continuous actions against a language encoding.

WPE writes each action as a string of numbers and embeds it with a pretrained language model
(TinyLlama). No pretrained weights can be fetched here, so :class:`TextActionEmbedder` keeps the
part of that pipeline that makes text differ from raw vectors — the numbers become digit tokens
of fixed precision, and the network has to read the value back out of the digits — and replaces
the language model by a small Transformer encoder trained from scratch with the world model.

An action ``[A]`` is written as ``A`` numbers of ``int_digits`` + ``frac_digits`` digits with a
sign, a point and a separator each, e.g. ``+1.25,-0.40,`` for ``A = 2`` with one integer and two
fraction digits: ``A * (int_digits + frac_digits + 3)`` tokens from a 14-symbol vocabulary.
Values beyond the largest writable number are clipped to it; the rest is rounded.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from wmjax.nn.layers import Attention, Dtype, Mlp, layer_norm, logical

PLUS, MINUS, POINT, SEPARATOR = 10, 11, 12, 13  # digits are tokens 0..9
VOCAB_SIZE = 14


def action_tokens(actions: jax.Array, int_digits: int = 1, frac_digits: int = 2) -> jax.Array:
  """``actions [..., A]`` (float) -> digit tokens ``[..., A * (int_digits + frac_digits + 3)]``."""
  largest = 10 ** (int_digits + frac_digits) - 1
  scaled = jnp.clip(jnp.round(jnp.abs(actions.astype(jnp.float32)) * 10 ** frac_digits), 0,
                    largest).astype(jnp.int32)  # [..., A]
  powers = 10 ** jnp.arange(int_digits + frac_digits - 1, -1, -1, dtype=jnp.int32)
  digits = (scaled[..., None] // powers) % 10  # [..., A, int + frac], most significant first
  sign = jnp.where(actions < 0, MINUS, PLUS)[..., None]
  shape = digits.shape[:-1] + (1,)
  point, separator = jnp.full(shape, POINT), jnp.full(shape, SEPARATOR)
  tokens = jnp.concatenate([sign, digits[..., :int_digits], point, digits[..., int_digits:],
                            separator], axis=-1)  # [..., A, int + frac + 3]
  return tokens.reshape(actions.shape[:-1] + (-1,))


class TextActionEmbedder(nn.Module):
  """Action -> digit tokens -> token + position embeddings -> ``num_layers`` pre-LN Transformer
  encoder blocks -> LayerNorm, mean over tokens -> Linear: ``[..., A] -> [..., D]``."""

  hidden_size: int
  width: int = 64
  num_layers: int = 2
  num_heads: int = 4
  int_digits: int = 1
  frac_digits: int = 2
  dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, actions: jax.Array) -> jax.Array:
    tokens = action_tokens(actions, self.int_digits, self.frac_digits)  # [..., L]
    lead, length = tokens.shape[:-1], tokens.shape[-1]
    embed_init = logical(nn.initializers.normal(0.02), "action", "embed")
    x = nn.Embed(VOCAB_SIZE, self.width, dtype=self.dtype, embedding_init=embed_init,
                 name="tokens")(tokens.reshape(-1, length))
    x = x + self.param("positions", embed_init, (length, self.width)).astype(self.dtype)  # [N, L, W]
    for i in range(self.num_layers):
      x = x + Attention(self.num_heads, dtype=self.dtype, name=f"attn_{i}")(layer_norm(x))[0]
      x = x + Mlp(self.width, 4 * self.width, dtype=self.dtype, name=f"mlp_{i}")(layer_norm(x))
    pooled = layer_norm(x).mean(axis=1)  # [N, W]
    out = nn.Dense(self.hidden_size, dtype=self.dtype,
                   kernel_init=logical(nn.initializers.xavier_uniform(), "action", "embed"),
                   bias_init=logical(nn.initializers.zeros, "embed"), name="proj")(pooled)
    return out.reshape(lead + (self.hidden_size,))
