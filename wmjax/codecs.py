"""Codecs between RGB frames and the space a world model diffuses in.

A world-model config names its codec in ``config.codec``:

  kind='pixel'  identity: the model sees RGB in [-1, 1]
  kind='patch'  ``patch_size`` x ``patch_size`` space-to-depth (``[H/p, W/p, 3 p^2]``), exact inverse
  kind='vae'    a diffusers AutoencoderKL folder (``path``): latents are
                ``(mean - shift_factor) * scaling_factor`` (or a sample instead of the mean), as
                IRASim (SDXL VAE) and WPE (SD3 VAE) use them; ``scaling_factor`` / ``shift_factor``
                default to the folder's config.json; ``dtype`` 'bfloat16' halves the cost.
                ``random_vae='sdxl' | 'sd3'`` instead builds a randomly initialised VAE of that
                layout and ``random_vae_widths`` (no files; for trying a recipe without weights).

``encode`` / ``decode`` map ``[..., H, W, 3] <-> [..., h, w, c]`` over any leading axes (e.g.
``[B, T]``), are pure JAX and can be jitted or called inside a jitted step; a VAE processes
``chunk`` frames at a time to bound memory.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import ml_collections
from einops import rearrange

from wmjax.config import codec_config  # noqa: F401  (config.codec with every field; re-exported)
from wmjax.nn.vae import AutoencoderKL, load_diffusers, random_vae

CODECS = ("pixel", "patch", "vae")


class Codec(Protocol):
  def latent_shape(self, frame_shape: tuple[int, int, int]) -> tuple[int, int, int]: ...
  def image_shape(self, latent_shape: tuple[int, int, int]) -> tuple[int, int, int]: ...
  def encode(self, frames: jax.Array, rng: jax.Array | None = None) -> jax.Array: ...
  def decode(self, latents: jax.Array) -> jax.Array: ...


def _check_frames(frames, channels: int, what: str) -> None:
  if frames.ndim < 3 or frames.shape[-1] != channels:
    raise ValueError(f"{what} must be [..., H, W, {channels}], got shape {tuple(frames.shape)}")


@dataclasses.dataclass(frozen=True)
class PixelCodec:
  """Identity: RGB frames in [-1, 1] are the model's space."""

  def latent_shape(self, frame_shape):
    return tuple(frame_shape)

  def image_shape(self, latent_shape):
    return tuple(latent_shape)

  def encode(self, frames, rng=None):
    del rng
    return jnp.asarray(frames, jnp.float32)

  def decode(self, latents):
    return jnp.asarray(latents, jnp.float32)


@dataclasses.dataclass(frozen=True)
class PatchCodec:
  """``p x p`` space-to-depth: ``[..., H, W, 3] -> [..., H/p, W/p, 3 p^2]`` (exact inverse)."""

  patch_size: int

  def latent_shape(self, frame_shape):
    h, w, c = frame_shape
    p = self.patch_size
    if h % p or w % p:
      raise ValueError(f"frames {h}x{w} are not divisible by the codec's patch size {p}")
    return (h // p, w // p, c * p * p)

  def image_shape(self, latent_shape):
    h, w, d = latent_shape
    p = self.patch_size
    return (h * p, w * p, d // (p * p))

  def encode(self, frames, rng=None):
    del rng
    frames = jnp.asarray(frames, jnp.float32)
    self.latent_shape(frames.shape[-3:])  # checks the patch size divides the frame
    p = self.patch_size
    return rearrange(frames, "... (h py) (w px) c -> ... h w (py px c)", py=p, px=p)

  def decode(self, latents):
    latents = jnp.asarray(latents, jnp.float32)
    p = self.patch_size
    return rearrange(latents, "... h w (py px c) -> ... (h py) (w px) c", py=p, px=p)


@dataclasses.dataclass(frozen=True, eq=False)
class VAECodec:
  """A diffusers AutoencoderKL (see the module doc). Two codecs of the same module and parameter
  objects with the same settings are equal, so that they share one compiled encode and decode."""

  module: AutoencoderKL
  params: Any
  scaling_factor: float
  shift_factor: float = 0.0
  sample: bool = False
  chunk: int = 16

  def _identity(self) -> tuple:
    return (id(self.module), id(self.params), self.scaling_factor, self.shift_factor, self.sample,
            self.chunk)

  def __eq__(self, other):
    return isinstance(other, VAECodec) and self._identity() == other._identity()

  def __hash__(self):
    return hash(self._identity())

  def latent_shape(self, frame_shape):
    h, w, _ = frame_shape
    f = self.module.config.downsample_factor
    if h % f or w % f:
      raise ValueError(f"frames {h}x{w} are not divisible by the VAE's downsampling factor {f}")
    return (h // f, w // f, self.module.config.latent_channels)

  def image_shape(self, latent_shape):
    h, w, _ = latent_shape
    f = self.module.config.downsample_factor
    return (h * f, w * f, self.module.config.in_channels)

  def encode(self, frames, rng=None):
    frames = jnp.asarray(frames, jnp.float32)
    _check_frames(frames, self.module.config.in_channels, "frames")
    if self.sample and rng is None:
      raise ValueError("this codec samples latents (sample=True): pass an rng")
    return _vae_encode(self, self.params, frames, rng)

  def decode(self, latents):
    latents = jnp.asarray(latents, jnp.float32)
    _check_frames(latents, self.module.config.latent_channels, "latents")
    return _vae_decode(self, self.params, latents)


def _over_frames(fn, x: jax.Array, chunk: int) -> jax.Array:
  """``fn`` (frames ``[B, H, W, C]`` -> ``[B, h, w, c]``) over ``x [B, ..., H, W, C]``: the
  leading (batch, possibly sharded) axis stays inside every call, the other leading axes are
  mapped over, about ``chunk`` frames per call."""
  lead = x.shape[:-3]
  b = lead[0] if lead else 1
  steps = jnp.moveaxis(x.reshape((b, -1) + x.shape[-3:]), 1, 0)  # [N, B, H, W, C]
  out = jax.lax.map(fn, steps, batch_size=max(1, min(chunk // b, steps.shape[0])))
  return jnp.moveaxis(out, 0, 1).reshape(lead + out.shape[2:])


@functools.partial(jax.jit, static_argnums=0)
def _vae_encode(codec: VAECodec, params, frames: jax.Array, rng) -> jax.Array:
  def one(images):
    return jnp.concatenate(codec.module.apply(params, images, method="encode"), -1)

  mean, logvar = jnp.split(_over_frames(one, frames, codec.chunk), 2, axis=-1)
  if codec.sample:
    mean = mean + jnp.exp(0.5 * logvar) * jax.random.normal(rng, mean.shape)
  return (mean - codec.shift_factor) * codec.scaling_factor


@functools.partial(jax.jit, static_argnums=0)
def _vae_decode(codec: VAECodec, params, latents: jax.Array) -> jax.Array:
  def one(latents):
    return codec.module.apply(params, latents, method="decode")

  z = latents / codec.scaling_factor + codec.shift_factor
  return jnp.clip(_over_frames(one, z, codec.chunk), -1.0, 1.0)


@functools.lru_cache(maxsize=4)
def _random_vae(layout: str, widths: tuple[int, ...], dtype) -> tuple[AutoencoderKL, Any]:
  """:func:`wmjax.nn.vae.random_vae`, made once per process for its arguments: every codec of a
  random-VAE config (training, evaluation, a loaded model) holds the same module and parameters,
  so they compile one encode and one decode between them."""
  return random_vae(layout, widths, dtype)


def _vae(config: ml_collections.ConfigDict) -> tuple[AutoencoderKL, Any]:
  """The VAE ``config.codec`` names: random (``random_vae``) or read from ``path``."""
  if config.random_vae:
    return _random_vae(config.random_vae, tuple(config.random_vae_widths), jnp.dtype(config.dtype))
  if not config.path or not os.path.exists(os.path.expanduser(config.path)):
    raise ValueError(f"codec.kind='vae' needs codec.path: a diffusers AutoencoderKL folder "
                     f"(config.json + diffusion_pytorch_model.safetensors), got "
                     f"{config.path!r}, which is not there; without the VAE, "
                     f"--config.codec.kind=pixel (load_model(..., overrides=[\"codec.kind="
                     f"'pixel'\"])) gives the model alone, on latents, and "
                     f"--config.codec.random_vae=sdxl (or sd3) a random tiny VAE to try a recipe "
                     f"with (its frame_shape to match; configs/bridge.py:tiny sets both)")
  return load_diffusers(config.path, jnp.dtype(config.dtype))


def make_codec(config: ml_collections.ConfigDict | None) -> Codec:
  """The codec a world-model config names (``config.codec``, schema
  :class:`wmjax.config.CodecConfig`, made by :func:`codec_config`; none means pixels)."""
  if config is None:
    return PixelCodec()
  kind = config.kind
  if kind == "pixel":
    return PixelCodec()
  if kind == "patch":
    return PatchCodec(int(config.patch_size))
  if kind != "vae":
    raise ValueError(f"codec.kind must be one of {CODECS}, got {kind!r}")
  module, params = _vae(config)
  scaling, shift = config.scaling_factor, config.shift_factor
  return VAECodec(module, params,
                  module.config.scaling_factor if scaling is None else float(scaling),
                  (module.config.shift_factor or 0.0) if shift is None else float(shift),
                  bool(config.sample), int(config.chunk))
