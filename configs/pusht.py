"""Push-T world model (gym-pusht) for policy evaluation and planning.

48x48 RGB renders (``wmjax.tasks.pusht.dataset``) of episodes whose agents push the T with the
scripted pusher at several noise levels (half of them), wander to random targets near the T, so
it is touched from every side (a quarter), or stand still (a quarter: the T must stay put when
nothing touches it). Each action, the agent's target position, is held for 4 control steps of
0.1 s and only the last frame is kept: one frame per decision, 10 frames an episode. Actions are
2-dim (standardised, with the sines and cosines of 2^k pi a beside each number) and each patch is
also told how far it lies from the place the action points at (``model.action_place``). An
ST-DiT with 4x4 patches (144 tokens a frame), each layer a temporal block then a spatial one,
with both absolute (sin-cos) and relative (RoPE) positions over the patch grid. Trained on
3-frame windows, two clean frames and the next one noised (IRASim's regime), to predict the clean
next frame (x0) at noise levels drawn logit-normal towards noise. Two context frames, because the
agent follows a PD controller (a second-order system): one frame does not tell its velocity. The
loss weighs the pixels within 3 of an object (agent, T, goal) of the last context frame 21 times
(``diffusion.object_weight=20, object_dilation=3``): the 3-pixel agent is under 1 % of the
frame, and an unweighted MSE is lowest for a model that drops it. Rollouts chain one-frame
blocks from two context frames, each in 8 DDIM steps with the temporal KV cache (2 steps leave
the sample near the blurred mean: the ranking of one training seed went from Pearson 0.45 to
0.84). The ``cpu`` profile samples with classifier-free guidance on the actions at scale 2 (the
network is trained with a tenth of its windows' actions dropped, ``model.action_dropout``): it
doubles the network calls and puts the imagined agent within about a pixel of the simulator's
instead of 6 px. ``experiments/pusht/RESULTS.md`` has the measurements behind each choice.

Profiles (``configs/pusht.py:PROFILE``):

- ``cpu`` (default): 1.9M parameters (depth 6, width 128), 1920 training episodes, 3000 steps of
  batch 16 in float32, sized for the whole experiment (``experiments/pusht/run.py``) on 2 CPU
  cores (about 55-65 minutes of training).
- ``latent``: the ``cpu`` profile diffusing in the 12x12x8 latents of a small autoencoder fitted to
  the run's own Push-T frames (``wmjax data train-codec --widths 16,32,64 --steps 1500
  --latent_channels 8``, 48x48x3 to 12x12x8) instead of in pixels: 1x1 patches (the same 144 tokens
  a frame), no clipping of x0 (latents are not in [-1, 1]), no object weights (in latents every
  value stands apart from its frame's median), 3000 steps. ``codec.path`` (the codec's folder) and
  ``data.latents_dir`` (the dataset pre-encoded by ``wmjax data encode``) are left empty:
  ``experiments/pusht/run.py --profile latent`` fits and fills both, or give them as overrides.
  Twice the 1500 steps it first had: the imagined agent within 2.5 px instead of 6-7 and the
  pushed T a little better (two training seeds). From step 750 a quarter of each batch trains on a
  last context frame the model generated itself (``diffusion.self_forcing=0.25``, windows of 4
  frames): screened at step 1500 in two training seeds, the untouched T's outline fades a third to
  a half slower and the T at the end of ``stay`` is 0.82 in both (0.71 and 0.77 without; at step
  3000 0.81 against 0.75); the pushed T is no better. Each self-forced step costs about a sixth
  more. The whole experiment, before self-forcing, took 61 minutes on 2 CPU cores (2026-11-28,
  alone, data to planning at K = 50); with it, 96 minutes alone on a 2-core Intel Xeon VM with
  AVX-512 (2026-11-29, Pearson 0.992, all five policies in order). Before self-forcing it ranks
  the five policies as the simulator does but for one swap of two policies within a standard error
  of each other (Pearson 0.949 and 0.936, Spearman 0.9); its pushed T still turns into a blob at
  contact (IoU 0.40 and 0.34 at the end of ``push``, copying the first frame 0.45), and planning
  in it gains at K = 5 and 10 no more than about twice its noise and nothing at K = 50.
- ``h100``: the same recipe and data at 32.5M parameters (depth 12, width 384, 6 heads) in
  bfloat16 with the fastest attention the GPU has, 3000 steps of batch 64 at learning rate 8e-4,
  checkpointed every 500 steps so that a run cut by a job limit resumes. Two training seeds ran
  side by side on one H200 in 7.4 minutes with evaluation (``experiments/pusht/RESULTS.md``),
  without guidance: guidance 2 measured no better there (its agent is already in place).
"""

import dataclasses

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config
from wmjax.tasks.pusht.dataset import PushTConfig


PROFILES = ("cpu", "latent", "h100")


def get_config(profile: str = "cpu") -> ml_collections.ConfigDict:
  if profile not in PROFILES:
    raise ValueError(f"Push-T profile must be one of {PROFILES}, got {profile!r}")
  config = ml_collections.ConfigDict()
  config.name = "pusht" if profile == "cpu" else f"pusht-{profile}"
  config.task = "wmjax.tasks.pusht"  # its dataset, metrics and coverage reward
  pusht = PushTConfig(train_episodes=1920, episode_length=10, chunk=1, action_repeat=4,
                      mix=(0.5, 0.25, 0.25))
  config.frame_shape = (pusht.image_size, pusht.image_size, 3)
  config.codec = codec_config(kind="pixel")

  config.data = ml_collections.ConfigDict(dict(
      dataset="pusht", data_dir="~/tensorflow_datasets", frames=3, train_stride=1,
      eval_stride=8, normalization="mean_std", num_workers=0, train_split="train",
      eval_split="test"))
  config.data.pusht = ml_collections.ConfigDict(dataclasses.asdict(pusht))
  config.model = model_config(
      in_channels=3, patch_size=4, depth=6, hidden_size=128, num_heads=4, num_frames=3,
      action_dim=2, cond="per_frame", action_embed_ratio=0, action_fourier_features=4,
      causal_temporal=True, temporal_first=True, spatial_pos="sincos+rope", action_dropout=0.1,
      action_place=(0, 1))
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="sigmoid", num_timesteps=1000, prediction="x0",
      regime="irasim", num_context=2, level_distribution="logit_normal", level_loc=1.0,
      object_weight=20.0, object_dilation=3))
  config.sampling = sampling_config(sampler="ddim", num_steps=8, matrix="autoregressive",
                                    context_level=0.0, clip_denoised=True, kv_cache=True,
                                    guidance_scale=2.0)
  config.rollout = ml_collections.ConfigDict(dict(context=2, horizon=1, short_actions=4))
  config.optim = optim_config(learning_rate=2e-3, schedule="cosine", warmup_steps=100,
                              total_steps=3000, b2=0.99, grad_clip=1.0, ema_decay=0.999)
  config.train = ml_collections.ConfigDict(dict(
      num_steps=3000, log_every=50, checkpoint_every=750, eval_every=3000, eval_windows=32,
      max_checkpoints=4,
      # fit before the first step: compiled memory against the device's limit (or the budget)
      auto_fit=True, memory_budget_gib=None))
  config.mesh = (-1, 1, 1)  # (data, fsdp, tensor)
  config.batch_size = 16  # global
  config.seed = 0
  if profile == "h100":
    config.model.update(depth=12, hidden_size=384, num_heads=6, dtype="bfloat16",
                        attention_impl="auto")
    config.optim.update(learning_rate=8e-4, total_steps=3000)
    config.train.update(num_steps=3000, checkpoint_every=500, eval_every=1000)
    config.data.num_workers = 4
    config.batch_size = 64
    config.sampling.guidance_scale = 1.0  # guidance 2 measured no better at this size
  if profile == "latent":
    latent_shape = (pusht.image_size // 4, pusht.image_size // 4, 8)
    config.codec.update(kind="vae", path="")  # a codec fitted to this data: run.py or overrides
    config.frame_shape = latent_shape
    config.model.update(in_channels=latent_shape[-1], patch_size=1)
    config.diffusion.object_weight = 0.0
    config.sampling.clip_denoised = False
    config.optim.total_steps = config.train.num_steps = config.train.eval_every = 3000
    config.train.checkpoint_every = 750  # four checkpoints: the ranking over training
    # from step 750 a quarter of each batch trains on a last context frame the model generated
    # itself (wmjax.train.self_forcing), from windows of one frame more
    config.data.frames = 4
    config.diffusion.update(self_forcing=0.25, self_forcing_start=750)
  return config
