"""A MetaWorld (Sawyer arm) world model seen by two cameras, for policy evaluation.

48x48 RGB renders of the third-person ``topview`` camera and the wrist camera ``gripperPOV``
(``wmjax.tasks.metaworld.dataset``), side by side in one 48x96 frame. The episodes are driven
by MetaWorld's scripted expert at action noise 0 / 0.2 / 0.4 / 0.6 (60 %), a random agent (20 %:
the arm comes at the objects from every side) and an idle agent (20 %: a still scene). Each
action (``[dx, dy, dz, grip]``) is held 5 control steps and one frame is kept per action: 22
frames an episode, time for the expert to finish the task.

The network is multi-view (``model.views = 2``): each view is patchified on its own 8x8 grid of
6x6 patches with the same 2-D positions (sin-cos and axial RoPE) plus a learned view embedding,
and one spatial attention runs over the 128 tokens of both views of a time step;
temporal attention is per token and causal, so rollouts keep a temporal KV cache. The recipe is
the Push-T one (``configs/pusht.py``): 3-frame windows, two clean frames and the next one noised,
x0 prediction at levels drawn logit-normal towards noise, Fourier features of each action number,
one frame per block from two context frames in 8 DDIM steps.

Profiles (``configs/metaworld.py:PROFILE``):

- ``cpu`` (default): ``button-press-v3``, 1.9M parameters (depth 6, width 128), 400 training
  episodes, 1800 steps of batch 16 in float32, sized for ``experiments/metaworld/run.py`` on 2
  CPU cores (about 55 minutes of training alone: 1.6 s a step).
- ``tiled``: the baseline of ``cpu``: the same frames, tokens and FLOPs, but one image (2-D
  positions over the whole 8x16 grid, no view embedding; ``model.views = 1``).
- ``drawer``: ``cpu`` on ``drawer-open-v3`` (an object the arm moves).
- ``h100``: 128x128 views (8x8 patches: 512 tokens a step), 32.5M parameters (depth 12, width
  384) in bfloat16 with the GPU's fastest attention, 1200 steps of batch 64 (2.7 times the
  ``cpu`` profile's samples), sized for ``experiments/metaworld/h100_device.sh``: data, reader,
  world model and policy evaluation in one call of under 10 minutes. Compiled for an H100 on a
  CPU (``wmjax compile --target h100``) the step takes 39.6 GiB and is predicted at 119 ms, so
  training is about 2.4 minutes. Not yet run on a card.
"""

import dataclasses

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config
from wmjax.data.oxe import spec_config
from wmjax.tasks.metaworld.dataset import MetaWorldConfig

PROFILES = ("cpu", "tiled", "drawer", "h100")


def get_config(profile: str = "cpu") -> ml_collections.ConfigDict:
  if profile not in PROFILES:
    raise ValueError(f"MetaWorld profile must be one of {PROFILES}, got {profile!r}")
  task = "drawer-open-v3" if profile == "drawer" else "button-press-v3"
  image_size = 128 if profile == "h100" else 48
  data = MetaWorldConfig(task=task, image_size=image_size)
  views = len(data.views)
  config = ml_collections.ConfigDict()
  config.name = "metaworld" if profile == "cpu" else f"metaworld-{profile}"
  config.task = "wmjax.tasks.metaworld"  # its dataset and per-view metrics
  config.frame_shape = (image_size, views * image_size, 3)  # the views side by side
  config.codec = codec_config(kind="pixel")

  config.data = ml_collections.ConfigDict(dict(
      dataset="metaworld", data_dir="~/tensorflow_datasets", frames=3, train_stride=1,
      eval_stride=8, normalization="mean_std", num_workers=0, train_split="train",
      eval_split="test",
      # the dataset's own spec (two views); data of three or more views names their keys here:
      # --config.data.spec.image_keys="('observation/image', 'observation/image_1', ...)"
      spec=spec_config(action_keys=())))
  config.data.metaworld = ml_collections.ConfigDict(dataclasses.asdict(data))
  config.model = model_config(
      in_channels=3, patch_size=6, depth=6, hidden_size=128, num_heads=4, num_frames=3,
      action_dim=4, cond="per_frame", action_embed_ratio=0, action_fourier_features=4,
      causal_temporal=True, temporal_first=True, spatial_pos="sincos+rope", action_dropout=0.1,
      views=1 if profile == "tiled" else views)
  config.diffusion = ml_collections.ConfigDict(dict(
      kind="gaussian", schedule="sigmoid", num_timesteps=1000, prediction="x0",
      regime="irasim", num_context=2, level_distribution="logit_normal", level_loc=1.0))
  config.sampling = sampling_config(sampler="ddim", num_steps=8, matrix="autoregressive",
                                    context_level=0.0, clip_denoised=True, kv_cache=True)
  config.rollout = ml_collections.ConfigDict(dict(context=2, horizon=1, short_actions=8))
  config.optim = optim_config(learning_rate=2e-3, schedule="cosine", warmup_steps=100,
                              total_steps=1800, b2=0.99, grad_clip=1.0, ema_decay=0.999)
  config.train = ml_collections.ConfigDict(dict(
      num_steps=1800, log_every=50, checkpoint_every=600, eval_every=1800, eval_windows=32,
      max_checkpoints=4, auto_fit=True, memory_budget_gib=None))
  config.mesh = (-1, 1, 1)  # (data, fsdp, tensor)
  config.batch_size = 16  # global
  config.seed = 0
  if profile == "h100":
    config.model.update(patch_size=8, depth=12, hidden_size=384, num_heads=6, dtype="bfloat16",
                        attention_impl="auto")
    config.optim.update(learning_rate=8e-4, total_steps=1200)
    config.train.update(num_steps=1200, checkpoint_every=600, eval_every=1200)
    config.data.num_workers = 4
    config.batch_size = 64
  return config
