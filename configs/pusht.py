"""Push-T world model (gym-pusht) for policy evaluation and planning.

48x48 RGB renders of scripted pushes at several noise levels (``wmjax.tasks.pusht.dataset``),
2-dim actions (the agent's target position, standardised), 6-frame windows; an ST-DiT with 4x4
patches (144 tokens a frame), WPE objective (per-frame noise levels, sigmoid schedule, v
prediction) with causal temporal attention, 10-step DDIM. Rollouts keep 2 context frames and
generate 4 per block, the length of the policies' action chunks.

Profiles (``configs/pusht.py:PROFILE``):

- ``cpu`` (default): 1.9M parameters (depth 6, width 128), 640 training episodes, 3000 steps of
  batch 8 in float32: about an hour on 2 CPU cores.
- ``h100``: 32.5M parameters (depth 12, width 384, 6 heads) in bfloat16 with the fastest attention
  the GPU has, 1920 training episodes, 5000 steps of batch 64 at learning rate 8e-4: about 7
  minutes and 22 GB on one H100 (11.6 steps/s), checkpointed every 500 steps so that a run cut
  by a 10-minute job limit resumes.
"""

import dataclasses

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config
from wmjax.tasks.pusht.dataset import PushTConfig


PROFILES = ("cpu", "h100")


def get_config(profile: str = "cpu") -> ml_collections.ConfigDict:
  if profile not in PROFILES:
    raise ValueError(f"Push-T profile must be one of {PROFILES}, got {profile!r}")
  config = ml_collections.ConfigDict()
  config.name = "pusht" if profile == "cpu" else f"pusht-{profile}"
  pusht = PushTConfig(train_episodes=640 if profile == "cpu" else 1920)
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
  if profile == "h100":
    config.model.update(depth=12, hidden_size=384, num_heads=6, dtype="bfloat16",
                        attention_impl="auto")
    config.optim.update(learning_rate=8e-4, total_steps=5000)
    config.train.update(num_steps=5000, checkpoint_every=500, eval_every=5000)
    config.data.num_workers = 4
    config.batch_size = 64
  return config
