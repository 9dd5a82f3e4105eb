"""The built-in default: a small world model of the WPE gridworld (appendix C.1) for CPU.

Pixel space (16x16 RGB, 2 squares of 4 px on the pixel grid -> 4-dim actions), 6-frame windows,
a 1.4M-parameter ST-DiT of 4 layers of width 96, each a temporal block then a spatial one, with
relative 2-D positions (axial RoPE) in the spatial blocks: moving a square by the action happens
in the spatial blocks after a temporal one, and with RoPE a move by an offset is one rotation of
the query (experiments/gridworld/RESULTS.md). WPE objective (per-frame noise levels, sigmoid
schedule) with causal temporal attention, predicting x0: v prediction weights the x0 error by
1 + SNR, which spends the loss on the nearly clean levels the sampler never visits, and x0
prediction reaches in 900 steps what v reached in 1800. Rollouts of 1 context frame + 5 actions,
sampled one frame after the other (autoregressive scheduling matrix), each frame in 2 DDIM steps
from the clean frames before it: the network then only ever predicts one step of the dynamics,
which it does far better than five at once. 900 steps of batch 8 take about 11 minutes on the
2-core CPU VM (1800 steps: 0.77 px instead of 0.89 short, twice the time).
"""

import dataclasses

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config
from wmjax.tasks.gridworld.dataset import GridworldConfig


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.name = "gridworld"
  config.frame_shape = (16, 16, 3)
  config.codec = codec_config(kind="pixel")  # the model sees RGB in [-1, 1]

  config.data = ml_collections.ConfigDict(dict(
      dataset="gridworld", data_dir="~/tensorflow_datasets", frames=6, train_stride=1,
      eval_stride=6, normalization="mean_std", num_workers=0, train_split="train",
      eval_split="test"))
  config.data.gridworld = ml_collections.ConfigDict(dataclasses.asdict(GridworldConfig()))
  config.model = model_config(
      in_channels=3, patch_size=2, depth=8, hidden_size=96, num_heads=4, num_frames=6,
      action_dim=4, cond="per_frame", action_embed_ratio=0, causal_temporal=True,
      temporal_first=True, spatial_pos="rope", action_dropout=0.1)
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="sigmoid", num_timesteps=1000, prediction="x0",
      regime="per_frame", num_context=1))
  config.sampling = sampling_config(sampler="ddim", num_steps=2, matrix="autoregressive",
                                    context_level=15.0, clip_denoised=True, kv_cache=True)
  config.rollout = ml_collections.ConfigDict(dict(context=1, horizon=5))
  config.optim = optim_config(learning_rate=3e-3, schedule="cosine", warmup_steps=100,
                              total_steps=900, b2=0.99, grad_clip=1.0, ema_decay=0.999)
  config.train = ml_collections.ConfigDict(dict(
      num_steps=900, log_every=50, checkpoint_every=300, eval_every=450, eval_windows=32,
      max_checkpoints=3,
      # fit before the first step: compiled memory against the device's limit (or the budget)
      auto_fit=True, memory_budget_gib=None))
  config.mesh = (-1, 1, 1)  # (data, fsdp, tensor)
  config.batch_size = 8  # global
  config.seed = 0
  return config
