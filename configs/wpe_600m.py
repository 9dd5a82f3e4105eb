"""WPE world model, 609M parameters (paper appendix A, table 5).

16 spatial + 16 temporal blocks, width 1024, 16 heads, patch 2, 16-channel SD3 latents of
256x256 frames (32x32), raw 7-dim actions through one linear layer, per-frame noise levels
(diffusion forcing), sigmoid schedule, v prediction, 10 DDIM steps, causal temporal attention.
"""

import ml_collections

from wmjax.config import model_config, optim_config, sampling_config


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.name = "wpe-600m"
  config.frame_shape = (32, 32, 16)

  config.model = model_config(
      in_channels=16, patch_size=2, depth=32, hidden_size=1024, num_heads=16, num_frames=20,
      action_dim=7, cond="per_frame", action_embed_ratio=0, causal_temporal=True)
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="sigmoid", num_timesteps=1000, prediction="v",
      regime="per_frame", num_context=1))
  # Causal temporal attention: the context's keys and values are computed once per block.
  config.sampling = sampling_config(sampler="ddim", num_steps=10, context_level=15.0,
                                    kv_cache=True)
  # WPE figure 7: context 9 and horizon 9 give the lowest arm MSE.
  config.rollout = ml_collections.ConfigDict(dict(context=9, horizon=9))
  # Table 5: AdamW lr 8e-5, betas (0.9, 0.99), weight decay 0.002, batch 16 (no clip or EMA
  # given; wmjax clips at 1.0 and keeps an EMA at 0.9999).
  config.optim = optim_config(learning_rate=8e-5, b2=0.99, weight_decay=0.002, grad_clip=1.0)
  config.batch_size = 16
  config.mesh = (-1, 1, 1)
  config.seed = 0
  return config
