"""AutoencoderKL in Flax Linen, laid out like diffusers' so that its weights load one to one.

The encoder and decoder follow ``diffusers.AutoencoderKL`` (SD 1.x / SDXL: 4 latent channels;
SD3 / Flux: 16 latent channels, no quant convs): a stack of ResNet blocks with stride-2
downsampling, a mid block with one single-head self-attention, GroupNorm(eps 1e-6) + SiLU, and a
mirror-image decoder with nearest-neighbour upsampling. Images are NHWC in [-1, 1]; the
encoder returns the Gaussian's mean and log-variance (clamped to [-30, 20] as in diffusers).
Scaling and shift factors are applied by :class:`wmjax.codecs.VAECodec`, not here.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import math
import os
import re
from typing import Sequence

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class VAEConfig:
  """The fields of a diffusers ``AutoencoderKL`` config.json that shape the network."""

  in_channels: int = 3
  out_channels: int = 3
  block_out_channels: tuple[int, ...] = (128, 256, 512, 512)
  layers_per_block: int = 2
  latent_channels: int = 4
  norm_num_groups: int = 32
  use_quant_conv: bool = True
  use_post_quant_conv: bool = True
  mid_block_add_attention: bool = True
  scaling_factor: float = 0.18215
  shift_factor: float | None = None

  @property
  def downsample_factor(self) -> int:
    return 2 ** (len(self.block_out_channels) - 1)

  @classmethod
  def from_diffusers(cls, config: dict) -> "VAEConfig":
    """From a diffusers config.json dict; a block type other than the plain encoder / decoder
    blocks, or an activation other than SiLU, is an error (not a silently different network)."""
    if config.get("_class_name", "AutoencoderKL") != "AutoencoderKL":
      raise ValueError(f"expected an AutoencoderKL config, got {config.get('_class_name')!r}")
    down = set(config.get("down_block_types", ["DownEncoderBlock2D"]))
    up = set(config.get("up_block_types", ["UpDecoderBlock2D"]))
    if down != {"DownEncoderBlock2D"} or up != {"UpDecoderBlock2D"}:
      raise ValueError(f"unsupported block types {sorted(down | up)}; wmjax supports "
                       f"DownEncoderBlock2D / UpDecoderBlock2D")
    if config.get("act_fn", "silu") != "silu":
      raise ValueError(f"unsupported act_fn {config['act_fn']!r}; wmjax supports 'silu'")
    fields = {f.name for f in dataclasses.fields(cls)}
    values = {k: v for k, v in config.items() if k in fields and v is not None}
    if "block_out_channels" in values:
      values["block_out_channels"] = tuple(values["block_out_channels"])
    values.setdefault("shift_factor", config.get("shift_factor"))
    return cls(**values)

  def to_diffusers(self) -> dict:
    """The diffusers config.json dict of this network (what :meth:`from_diffusers` reads)."""
    blocks = len(self.block_out_channels)
    config = {"_class_name": "AutoencoderKL", "act_fn": "silu",
              "down_block_types": ["DownEncoderBlock2D"] * blocks,
              "up_block_types": ["UpDecoderBlock2D"] * blocks}
    config.update(dataclasses.asdict(self), block_out_channels=list(self.block_out_channels))
    return config


def _group_norm(config: VAEConfig, name: str) -> nn.GroupNorm:
  return nn.GroupNorm(num_groups=config.norm_num_groups, epsilon=1e-6, use_fast_variance=False,
                      name=name)


def _conv(features: int, kernel: int, name: str, dtype, strides: int = 1, padding="SAME"):
  return nn.Conv(features, (kernel, kernel), strides=(strides, strides), padding=padding,
                 dtype=dtype, name=name)


class ResnetBlock(nn.Module):
  """GroupNorm -> SiLU -> conv3x3, twice, plus a (1x1-projected) shortcut: ``[B, H, W, C]``."""

  config: VAEConfig
  features: int
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    h = _conv(self.features, 3, "conv1", self.dtype)(nn.silu(_group_norm(self.config, "norm1")(x)))
    h = _conv(self.features, 3, "conv2", self.dtype)(nn.silu(_group_norm(self.config, "norm2")(h)))
    if x.shape[-1] != self.features:
      x = _conv(self.features, 1, "conv_shortcut", self.dtype)(x)
    return x + h


class MidAttention(nn.Module):
  """Single-head self-attention over all positions, GroupNorm first, residual: ``[B, H, W, C]``."""

  config: VAEConfig
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    b, h, w, c = x.shape
    y = _group_norm(self.config, "group_norm")(x).reshape(b, h * w, c)
    q, k, v = (nn.Dense(c, dtype=self.dtype, name=n)(y) for n in ("to_q", "to_k", "to_v"))
    logits = jnp.einsum("bqc,bkc->bqk", q, k).astype(jnp.float32) / jnp.sqrt(c)
    weights = jax.nn.softmax(logits, axis=-1).astype(v.dtype)
    out = nn.Dense(c, dtype=self.dtype, name="to_out_0")(jnp.einsum("bqk,bkc->bqc", weights, v))
    return x + out.reshape(b, h, w, c)


class MidBlock(nn.Module):
  config: VAEConfig
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    c = x.shape[-1]
    x = ResnetBlock(self.config, c, self.dtype, name="resnets_0")(x)
    if self.config.mid_block_add_attention:
      x = MidAttention(self.config, self.dtype, name="attentions_0")(x)
    return ResnetBlock(self.config, c, self.dtype, name="resnets_1")(x)


class Encoder(nn.Module):
  """Images ``[B, H, W, C_in]`` -> mean and log-variance ``[B, H/f, W/f, latent]`` each."""

  config: VAEConfig
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    cfg = self.config
    x = _conv(cfg.block_out_channels[0], 3, "conv_in", self.dtype)(x.astype(self.dtype))
    for i, features in enumerate(cfg.block_out_channels):
      for j in range(cfg.layers_per_block):
        x = ResnetBlock(cfg, features, self.dtype, name=f"down_blocks_{i}_resnets_{j}")(x)
      if i < len(cfg.block_out_channels) - 1:
        x = jnp.pad(x, ((0, 0), (0, 1), (0, 1), (0, 0)))  # diffusers pads right / bottom only
        x = _conv(features, 3, f"down_blocks_{i}_downsamplers_0_conv", self.dtype, strides=2,
                  padding="VALID")(x)
    x = MidBlock(cfg, self.dtype, name="mid_block")(x)
    x = nn.silu(_group_norm(cfg, "conv_norm_out")(x))
    moments = _conv(2 * cfg.latent_channels, 3, "conv_out", self.dtype)(x)
    if cfg.use_quant_conv:
      moments = _conv(2 * cfg.latent_channels, 1, "quant_conv", self.dtype)(moments)
    mean, logvar = jnp.split(moments.astype(jnp.float32), 2, axis=-1)
    return mean, jnp.clip(logvar, -30.0, 20.0)


class Decoder(nn.Module):
  """Latents ``[B, h, w, latent]`` -> images ``[B, h*f, w*f, C_out]``."""

  config: VAEConfig
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, z: jax.Array) -> jax.Array:
    cfg = self.config
    z = z.astype(self.dtype)
    if cfg.use_post_quant_conv:
      z = _conv(cfg.latent_channels, 1, "post_quant_conv", self.dtype)(z)
    x = _conv(cfg.block_out_channels[-1], 3, "conv_in", self.dtype)(z)
    x = MidBlock(cfg, self.dtype, name="mid_block")(x)
    channels = list(reversed(cfg.block_out_channels))
    for i, features in enumerate(channels):
      for j in range(cfg.layers_per_block + 1):
        x = ResnetBlock(cfg, features, self.dtype, name=f"up_blocks_{i}_resnets_{j}")(x)
      if i < len(channels) - 1:
        x = jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)  # nearest-neighbour x2
        x = _conv(features, 3, f"up_blocks_{i}_upsamplers_0_conv", self.dtype)(x)
    x = nn.silu(_group_norm(cfg, "conv_norm_out")(x))
    return _conv(cfg.out_channels, 3, "conv_out", self.dtype)(x).astype(jnp.float32)


class AutoencoderKL(nn.Module):
  """``encode(images) -> (mean, logvar)`` and ``decode(latents) -> images``, NHWC, unscaled."""

  config: VAEConfig
  dtype: jnp.dtype = jnp.float32

  def setup(self):
    self.encoder = Encoder(self.config, self.dtype)
    self.decoder = Decoder(self.config, self.dtype)

  def encode(self, images: jax.Array) -> tuple[jax.Array, jax.Array]:
    return self.encoder(images)

  def decode(self, latents: jax.Array) -> jax.Array:
    return self.decoder(latents)

  def __call__(self, images: jax.Array) -> jax.Array:
    """Reconstruction through the mean (used to initialise every parameter at once)."""
    return self.decode(self.encode(images)[0])


def _images(config: VAEConfig) -> jax.Array:
  """The smallest batch of images ``[1, 8 f, 8 f, in_channels]`` that initialises every parameter
  (f: the downsampling factor)."""
  size = 8 * config.downsample_factor
  return jnp.zeros((1, size, size, config.in_channels))


# ----------------------------------------------------------------------------- random weights

# What a diffusers VAE layout fixes besides its widths: latent channels, quant convs, scaling and
# shift (SD 1.x / SDXL with SDXL's scaling; SD3). The names are CodecConfig.random_vae's choices.
LAYOUTS = {
    "sdxl": dict(latent_channels=4, scaling_factor=0.13025),
    "sd3": dict(latent_channels=16, scaling_factor=1.5305, shift_factor=0.0609,
                use_quant_conv=False, use_post_quant_conv=False),
}


def random_vae(layout: str, widths: Sequence[int], dtype=jnp.float32, seed: int = 0
               ) -> tuple[AutoencoderKL, dict]:
  """A randomly initialised AutoencoderKL of a diffusers ``layout`` (:data:`LAYOUTS`) with block
  ``widths`` (downsampling by ``2 ** (len(widths) - 1)``), one ResNet block a level and
  GroupNorm groups dividing every width: (module, params), the same for the same arguments, no
  files. For trying latent recipes without downloaded weights; its latents mean nothing."""
  if layout not in LAYOUTS:
    raise ValueError(f"random VAE layout must be one of {sorted(LAYOUTS)}, got {layout!r}")
  widths = tuple(int(w) for w in widths)
  if not widths or min(widths) < 1:
    raise ValueError(f"random VAE widths must be one or more positive ints, got {widths}")
  config = VAEConfig(block_out_channels=widths, layers_per_block=1,
                     norm_num_groups=math.gcd(32, *widths), **LAYOUTS[layout])
  module = AutoencoderKL(config, dtype)
  # one compiled program: run eagerly, every convolution and norm of the forward pass that
  # initialises it would compile as a program of its own (the same parameters to the bit)
  return module, jax.jit(module.init)(jax.random.key(seed), _images(config))


# ----------------------------------------------------------------------------- diffusers weights

_LEGACY_ATTENTION = {"to_q": "query", "to_k": "key", "to_v": "value", "to_out.0": "proj_attn"}


def diffusers_key(path: tuple[str, ...]) -> str:
  """Flax parameter path -> the diffusers state-dict key, e.g.
  ``('encoder', 'down_blocks_0_resnets_1', 'conv1', 'kernel')`` ->
  ``encoder.down_blocks.0.resnets.1.conv1.weight``."""
  *modules, leaf = path
  if modules[-1] in ("quant_conv", "post_quant_conv"):
    modules = modules[-1:]  # top level in diffusers
  names = [re.sub(r"_(\d+)(_|$)", lambda m: f".{m[1]}{'.' if m[2] else ''}", m) for m in modules]
  return ".".join(names + ["bias" if leaf == "bias" else "weight"])


def _to_flax(name: str, value: np.ndarray, expected: tuple[int, ...]) -> np.ndarray:
  """A torch tensor -> the Flax layout: conv [O, I, kh, kw] -> [kh, kw, I, O]; linear [O, I]
  (or a 1x1 conv [O, I, 1, 1], as in old checkpoints) -> [I, O]."""
  if value.ndim == 4 and len(expected) == 4:
    value = value.transpose(2, 3, 1, 0)
  elif value.ndim in (2, 4) and len(expected) == 2:
    value = value.reshape(value.shape[:2]).T
  if tuple(value.shape) != tuple(expected):
    raise ValueError(f"{name}: shape {tuple(value.shape)} (in the Flax layout) does not match the "
                     f"model's {tuple(expected)}")
  return value


def convert_diffusers_state(state: dict[str, np.ndarray], abstract_params: dict) -> dict:
  """A diffusers AutoencoderKL state dict -> Flax parameters shaped like ``abstract_params``.
  A missing or unused key, or a shape mismatch, is an error that names the parameter."""
  state = dict(state)
  for key in list(state):  # old checkpoints name the attention projections differently
    for new, old in _LEGACY_ATTENTION.items():
      if key.endswith(f".attentions.0.{old}.weight") or key.endswith(f".attentions.0.{old}.bias"):
        state[key.replace(f".{old}.", f".{new}.")] = state.pop(key)
  flat = flax.traverse_util.flatten_dict(abstract_params)
  converted, missing = {}, []
  for path, leaf in flat.items():
    key = diffusers_key(path)
    if key not in state:
      missing.append(key)
      continue
    value = np.asarray(state.pop(key)).astype(np.float32)
    converted[path] = _to_flax(key, value, leaf.shape).astype(leaf.dtype)
  if missing:
    raise ValueError(f"the weights lack {len(missing)} parameter(s) of the model, e.g. "
                     f"{missing[:5]}; is the config.json the one of these weights?")
  if state:
    raise ValueError(f"the weights hold {len(state)} key(s) the model has no parameter for, e.g. "
                     f"{sorted(state)[:5]}")
  return flax.traverse_util.unflatten_dict(converted)


def save_diffusers(folder: str, config: VAEConfig, params: dict) -> str:
  """Write an AutoencoderKL as a diffusers folder (``config.json`` +
  ``diffusion_pytorch_model.safetensors``, torch layouts) that :func:`load_diffusers` and
  ``diffusers.AutoencoderKL.from_pretrained`` read; returns the folder. ``params`` are the
  module's variables (``{"params": ...}``)."""
  from safetensors.numpy import save_file

  os.makedirs(folder, exist_ok=True)
  state = {}
  for path, leaf in flax.traverse_util.flatten_dict(params["params"]).items():
    value = np.asarray(leaf, np.float32)
    if value.ndim == 4:  # conv [kh, kw, I, O] -> [O, I, kh, kw]
      value = value.transpose(3, 2, 0, 1)
    elif value.ndim == 2:  # linear [I, O] -> [O, I]
      value = value.T
    state[diffusers_key(path)] = np.ascontiguousarray(value)
  save_file(state, os.path.join(folder, "diffusion_pytorch_model.safetensors"),
            metadata={"format": "pt"})
  with open(os.path.join(folder, "config.json"), "w") as f:
    json.dump(config.to_diffusers(), f, indent=2)
  return folder


def load_diffusers(path: str, dtype=jnp.float32) -> tuple[AutoencoderKL, dict]:
  """A diffusers AutoencoderKL folder (``config.json`` + ``diffusion_pytorch_model.safetensors``,
  as written by ``save_pretrained``; a ``vae/`` subfolder of a pipeline is found too) ->
  (module, params). No torch needed; ``dtype`` is the compute dtype (params stay float32)."""
  import safetensors

  folder = os.path.expanduser(path)
  if not os.path.isfile(os.path.join(folder, "config.json")) and os.path.isdir(
      os.path.join(folder, "vae")):
    folder = os.path.join(folder, "vae")
  config_path = os.path.join(folder, "config.json")
  if not os.path.isfile(config_path):
    raise FileNotFoundError(f"{path} has no config.json (expected a diffusers AutoencoderKL "
                            f"folder)")
  weights = sorted(glob.glob(os.path.join(folder, "*.safetensors")))
  preferred = [w for w in weights if os.path.basename(w) == "diffusion_pytorch_model.safetensors"]
  if not weights:
    raise FileNotFoundError(f"{folder} has no .safetensors weights")
  with open(config_path) as f:
    config = VAEConfig.from_diffusers(json.load(f))
  state = {}
  with safetensors.safe_open((preferred or weights)[0], framework="flax") as f:  # bf16 too
    for key in f.keys():
      state[key] = f.get_tensor(key)
  module = AutoencoderKL(config, dtype)
  abstract = jax.eval_shape(module.init, jax.random.key(0), _images(config))["params"]
  return module, {"params": convert_diffusers_state(state, abstract)}
