"""IRASim world model (Frame-Ada ST-DiT, SDXL latents, linear-eps diffusion, DDIM sampling).

``get_config('S' | 'B' | 'L' | 'XL')`` gives IRASim-S/2, B/2, L/2, XL/2 (table 11 of the paper):
4-channel 32x40 latents (256x320 frames through the SDXL VAE), 16-frame windows, 7-dim actions.
``get_config('XL,rt1')`` (or ``bridge``, ``language_table``) adds the training recipe for that
dataset: its data section and the SDXL VAE codec (``configs/rt1.py`` etc. are these).
``get_config('XL,rt1,video_ada')`` is the Video-Ada variant (one embedding of the whole
trajectory conditions every block) instead of Frame-Ada (``frame_ada``, the default).
``get_config('tiny,rt1')`` is a recipe at smoke-run size, without downloaded weights: a random
SDXL-layout VAE and a tiny model on small frames (:func:`wmjax.config.tiny_profile`).
"""

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import model_config, optim_config, sampling_config, tiny_profile

# size: (blocks = spatial + temporal, hidden size, heads); ~33M / 132M / 461M / 679M parameters.
SIZES = {"S": (12, 384, 6), "B": (12, 768, 12), "L": (24, 1024, 16), "XL": (28, 1152, 16)}

# IRASim's datasets: Open-X name, published location, frame size, action dim, held-out split.
# RT-1 and Language-Table publish only a train split; the last 5 % of it is held out.
DATASETS = {
    "rt1": ("fractal20220817_data", "gs://gresearch/robotics/fractal20220817_data/0.1.0",
            (256, 320), 7, ("train[:95%]", "train[95%:]")),
    "bridge": ("bridge", "gs://gresearch/robotics/bridge/0.1.0", (256, 320), 7,
               ("train", "test")),
    "language_table": ("language_table", "gs://gresearch/robotics/language_table/0.0.1",
                       (288, 512), 2, ("train[:95%]", "train[95%:]")),
}

SDXL_VAE_SCALING = 0.13025

# variant: the model's action conditioning (wmjax.nn.dit, cond)
VARIANTS = {"frame_ada": "frame", "video_ada": "video"}


def get_config(arg: str = "XL") -> ml_collections.ConfigDict:
  size, dataset, variant = (arg.split(",") + ["", ""])[:3]
  if size == "tiny":
    if not dataset:
      raise ValueError("the tiny profile shrinks a recipe: name its dataset, e.g. 'tiny,rt1'")
    return tiny_profile(get_config(f"S,{dataset},{variant}"), "sdxl", f"irasim-tiny-{dataset}")
  if size not in SIZES:
    raise ValueError(f"IRASim size must be one of {sorted(SIZES)} or 'tiny', got {size!r}")
  variant = variant or "frame_ada"
  if variant not in VARIANTS:
    raise ValueError(f"IRASim variant must be one of {sorted(VARIANTS)}, got {variant!r}")
  depth, hidden, heads = SIZES[size]
  config = ml_collections.ConfigDict()
  config.name = f"irasim-{size}/2" + ("-video-ada" if variant == "video_ada" else "")
  config.frame_shape = (32, 40, 4)  # what the network sees: SDXL latents of 256x320 frames

  config.model = model_config(
      in_channels=4, patch_size=2, depth=depth, hidden_size=hidden, num_heads=heads,
      num_frames=16, action_dim=7, cond=VARIANTS[variant], action_embed_ratio=4)
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
  if dataset:
    add_recipe(config, dataset)
  return config


def add_recipe(config: ml_collections.ConfigDict, dataset: str) -> None:
  """The data, codec and training-loop sections of IRASim's recipe for ``dataset``."""
  if dataset not in DATASETS:
    raise ValueError(f"IRASim dataset must be one of {sorted(DATASETS)}, got {dataset!r}")
  name, location, resolution, action_dim, (train_split, eval_split) = DATASETS[dataset]
  config.name = f"{config.name}-{dataset}"
  # The SDXL VAE as a diffusers folder (e.g. stabilityai/sdxl-vae, downloaded beforehand).
  config.codec = codec_config(kind="vae", path="~/models/sdxl-vae", dtype="bfloat16",
                              scaling_factor=SDXL_VAE_SCALING)
  config.frame_shape = (resolution[0] // 8, resolution[1] // 8, 4)
  config.model.action_dim = action_dim
  # Windows of 16 frames, stride 1 for training and 16 for evaluation (IRASim appendix 11).
  # Training reads ArrayRecord: `wmjax data convert` the published TFRecord once, then point
  # builder_dir at the copy (or latents_dir at `wmjax data encode` output).
  config.data = ml_collections.ConfigDict(dict(
      dataset=name, builder_dir=location, latents_dir="", resolution=resolution, frames=16,
      train_stride=1, eval_stride=16, normalization="mean_std", num_workers=8,
      train_split=train_split, eval_split=eval_split))
  config.train = ml_collections.ConfigDict(dict(
      num_steps=300_000, log_every=100, checkpoint_every=5_000, eval_every=5_000,
      eval_windows=16, max_checkpoints=3,
      # fit before the first step: compiled memory against the device's limit (or the budget)
      auto_fit=True, memory_budget_gib=None))
