"""IRASim world model (Frame-Ada ST-DiT, SDXL latents, linear-eps diffusion, DDIM sampling).

``get_config('S' | 'B' | 'L' | 'XL')`` gives IRASim-S/2, B/2, L/2, XL/2 (table 11 of the paper):
4-channel 32x40 latents (256x320 frames through the SDXL VAE), 16-frame windows, 7-dim actions.
"""

import ml_collections

from wmjax.config import model_config, optim_config, sampling_config

# size: (blocks = spatial + temporal, hidden size, heads); ~33M / 132M / 461M / 679M parameters.
SIZES = {"S": (12, 384, 6), "B": (12, 768, 12), "L": (24, 1024, 16), "XL": (28, 1152, 16)}


def get_config(size: str = "XL") -> ml_collections.ConfigDict:
  if size not in SIZES:
    raise ValueError(f"IRASim size must be one of {sorted(SIZES)}, got {size!r}")
  depth, hidden, heads = SIZES[size]
  config = ml_collections.ConfigDict()
  config.name = f"irasim-{size}/2"
  config.frame_shape = (32, 40, 4)  # what the network sees: SDXL latents of 256x320 frames

  config.model = model_config(
      in_channels=4, patch_size=2, depth=depth, hidden_size=hidden, num_heads=heads,
      num_frames=16, action_dim=7, cond="frame", action_embed_ratio=4)
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="linear", num_timesteps=1000, prediction="eps",
      regime="irasim", num_context=1))
  # IRASim samples with PNDM-50; wmjax uses DDIM-50. Context frames were clean in training.
  config.sampling = sampling_config(sampler="ddim", num_steps=50, context_level=0.0)
  config.rollout = ml_collections.ConfigDict(dict(context=1, horizon=15))
  # Table 10: AdamW lr 1e-4 constant, betas (0.9, 0.999), no weight decay, clip 0.1, EMA 0.9999,
  # batch 64.
  config.optim = optim_config()
  config.batch_size = 64
  config.mesh = (-1, 1, 1)
  config.seed = 0
  return config
