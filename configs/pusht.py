"""Push-T world model (gym-pusht) for policy evaluation and planning on CPU.

48x48 RGB renders of scripted pushes at several noise levels (``wmjax.data.pusht``), 2-dim
actions (the agent's target position, standardised), 6-frame windows; a 1.0M-parameter ST-DiT
with 4x4 patches (144 tokens a frame), WPE objective (per-frame noise levels, sigmoid schedule,
v prediction) with causal temporal attention, 10-step DDIM. Rollouts keep 2 context frames and
generate 4 per block, the length of the policies' action chunks.
"""

import dataclasses

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config
from wmjax.tasks.pusht.dataset import PushTConfig


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.name = "pusht"
  pusht = PushTConfig()
  config.frame_shape = (pusht.image_size, pusht.image_size, 3)
  config.codec = codec_config(kind="pixel")

  config.data = ml_collections.ConfigDict(dict(
      dataset="pusht", data_dir="~/tensorflow_datasets", frames=6, train_stride=1,
      eval_stride=6, normalization="mean_std", num_workers=0, train_split="train",
      eval_split="test"))
  config.data.pusht = ml_collections.ConfigDict(dataclasses.asdict(pusht))
  config.model = model_config(
      in_channels=3, patch_size=4, depth=6, hidden_size=128, num_heads=4, num_frames=6,
      action_dim=2, cond="per_frame", action_embed_ratio=0, causal_temporal=True,
      action_dropout=0.1)
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="sigmoid", num_timesteps=1000, prediction="v",
      regime="per_frame", num_context=2))
  config.sampling = sampling_config(sampler="ddim", num_steps=10, context_level=15.0,
                                    clip_denoised=True, kv_cache=True)
  config.rollout = ml_collections.ConfigDict(dict(context=2, horizon=4))
  config.optim = optim_config(learning_rate=2e-3, schedule="cosine", warmup_steps=100,
                              total_steps=3000, b2=0.99, grad_clip=1.0, ema_decay=0.999)
  config.train = ml_collections.ConfigDict(dict(
      num_steps=3000, log_every=50, checkpoint_every=500, eval_every=1000, eval_windows=32,
      max_checkpoints=3,
      # fit before the first step: compiled memory against the device's limit (or the budget)
      auto_fit=True, memory_budget_gib=None))
  config.mesh = (-1, 1, 1)  # (data, fsdp, tensor)
  config.batch_size = 8  # global
  config.seed = 0
  return config
