"""Encode and decode frames/s of the codecs, with the full-size diffusers VAE layouts (random
weights: speed does not depend on them); writes JSON.

  python benchmarks/codec.py --codec sdxl --resolution 256,320 --batch 4 [--dtype bfloat16]

Codecs: ``pixel``, ``patch`` (4x4 space-to-depth), ``sdxl`` (SD / SDXL AutoencoderKL: channels
128-256-512-512, 2 ResNets per level, 4 latent channels) and ``sd3`` (the same with 16 latent
channels and no quant convs). Times are medians after one compile run; frames/s counts frames of
``--batch`` x ``--frames``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import jax
import jax.numpy as jnp

from common import median_seconds
from wmjax.codecs import PatchCodec, PixelCodec, VAECodec
from wmjax.nn.vae import AutoencoderKL, VAEConfig

LAYOUTS = {
    "sdxl": VAEConfig(latent_channels=4, scaling_factor=0.13025),
    "sd3": VAEConfig(latent_channels=16, use_quant_conv=False, use_post_quant_conv=False,
                     scaling_factor=1.5305, shift_factor=0.0609),
}


def make(name: str, dtype: str, chunk: int):
  if name == "pixel":
    return PixelCodec()
  if name == "patch":
    return PatchCodec(4)
  config = LAYOUTS[name]
  module = AutoencoderKL(config, jnp.dtype(dtype))
  params = jax.jit(module.init)(jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
  return VAECodec(module, params, config.scaling_factor, config.shift_factor or 0.0, chunk=chunk)


def benchmark(name: str, resolution: tuple[int, int], batch: int, frames: int, dtype: str,
              chunk: int, repeats: int) -> dict:
  codec = make(name, dtype, chunk)
  x = jax.random.uniform(jax.random.key(1), (batch, frames) + resolution + (3,), minval=-1.0)
  encode = jax.jit(lambda v: codec.encode(v))
  encode_s, encode_compile_s = median_seconds(lambda: encode(x), repeats)
  latents = encode(x)
  decode = jax.jit(lambda z: codec.decode(z))
  decode_s, decode_compile_s = median_seconds(lambda: decode(latents), repeats)
  n = batch * frames
  return {
      "codec": name, "dtype": dtype, "resolution": list(resolution), "batch": batch,
      "frames": frames, "chunk": chunk, "latent_shape": list(latents.shape[2:]),
      "device": jax.devices()[0].device_kind, "platform": jax.default_backend(),
      "host": platform.node(), "jax": jax.__version__,
      "encode_s": encode_s, "encode_frames_per_s": n / encode_s,
      "encode_compile_s": encode_compile_s, "decode_s": decode_s,
      "decode_frames_per_s": n / decode_s, "decode_compile_s": decode_compile_s,
  }


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--codec", choices=["pixel", "patch", *LAYOUTS], required=True)
  parser.add_argument("--resolution", default="256,320", help="H,W of the frames")
  parser.add_argument("--batch", type=int, default=2)
  parser.add_argument("--frames", type=int, default=2, help="frames per video")
  parser.add_argument("--dtype", default="float32", help="compute dtype of the VAE")
  parser.add_argument("--chunk", type=int, default=16, help="frames per VAE call")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--out", default=None)
  args = parser.parse_args()
  resolution = tuple(int(v) for v in args.resolution.split(","))
  result = benchmark(args.codec, resolution, args.batch, args.frames, args.dtype, args.chunk,
                     args.repeats)
  print(json.dumps(result, indent=2))
  out = args.out or os.path.join(
      os.path.dirname(__file__), "results",
      f"codec-{args.codec}-{args.dtype}-{resolution[0]}x{resolution[1]}-"
      f"{jax.default_backend()}-b{args.batch * args.frames}.json")
  with open(out, "w") as f:
    json.dump(result, f, indent=2)
  print(f"wrote {out}")


if __name__ == "__main__":
  main()
