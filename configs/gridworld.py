"""The built-in default: a small world model of the WPE gridworld (appendix C.1) for CPU.

Pixel space (16x16 RGB, 2 squares of 4 px on the pixel grid -> 4-dim actions), a 1.4M-parameter
ST-DiT of 4 layers of width 96, each a temporal block then a spatial one, with relative 2-D
positions (axial RoPE) in the spatial blocks: moving a square by the action happens in the
spatial blocks after a temporal one, and with RoPE a move by an offset is one rotation of the
query (experiments/gridworld/RESULTS.md). Trained on 2-frame windows, the first clean and the
second noised (IRASim's regime): every training sample is the one prediction sampling asks for,
the next frame from a clean past and its action. Predicting x0 (v prediction weights the x0 error
by 1 + SNR and spends the loss on nearly clean levels the sampler never visits), with the noise
levels drawn logit-normal around level 730 (``level_loc=1``) rather than uniformly: the high
levels are where the square has to come from the action. Each action number enters with the sines
and cosines of 2^k pi a (k < 4) beside it (``action_fourier_features=4``): the move is
``round(v)`` pixels, a step function of the action that a linear embedding of ``a`` alone cannot
draw sharply (half the error, experiments/gridworld/RESULTS.md). Rollouts chain 1-frame blocks, each in
2 DDIM steps; the short protocol is 1 frame + 5 actions. 1200 steps of batch 16 take about
7-8 minutes on the 2-core CPU VM (1500 steps: a little better, 0.25 / 0.33 px short over two
seeds against 0.39 / 0.38, but past the quickstart's 10 minutes on a slow VM).
"""

import dataclasses

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config
from wmjax.tasks.gridworld.dataset import GridworldConfig


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.name = "gridworld"
  config.task = "wmjax.tasks.gridworld"  # its dataset and square metrics
  config.frame_shape = (16, 16, 3)
  config.codec = codec_config(kind="pixel")  # the model sees RGB in [-1, 1]

  config.data = ml_collections.ConfigDict(dict(
      dataset="gridworld", data_dir="~/tensorflow_datasets", frames=2, train_stride=1,
      eval_stride=6, normalization="mean_std", num_workers=0, train_split="train",
      eval_split="test"))
  config.data.gridworld = ml_collections.ConfigDict(dataclasses.asdict(GridworldConfig()))
  config.model = model_config(
      in_channels=3, patch_size=2, depth=8, hidden_size=96, num_heads=4, num_frames=2,
      action_dim=4, cond="per_frame", action_embed_ratio=0, action_fourier_features=4,
      causal_temporal=True,
      temporal_first=True, spatial_pos="rope", action_dropout=0.1)
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="sigmoid", num_timesteps=1000, prediction="x0",
      regime="irasim", num_context=1, level_distribution="logit_normal", level_loc=1.0))
  config.sampling = sampling_config(sampler="ddim", num_steps=2, matrix="autoregressive",
                                    context_level=0.0, clip_denoised=True, kv_cache=True)
  config.rollout = ml_collections.ConfigDict(dict(context=1, horizon=1, short_actions=5))
  config.optim = optim_config(learning_rate=3e-3, schedule="cosine", warmup_steps=100,
                              total_steps=1200, b2=0.99, grad_clip=1.0, ema_decay=0.999)
  config.train = ml_collections.ConfigDict(dict(
      num_steps=1200, log_every=50, checkpoint_every=400, eval_every=1200, eval_windows=32,
      max_checkpoints=3,
      # fit before the first step: compiled memory against the device's limit (or the budget)
      auto_fit=True, memory_budget_gib=None))
  config.mesh = (-1, 1, 1)  # (data, fsdp, tensor)
  config.batch_size = 16  # global
  config.seed = 0
  return config
