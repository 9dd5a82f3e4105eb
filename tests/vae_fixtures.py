"""Small random-weight diffusers AutoencoderKL folders (needs torch and diffusers, test extra)."""

import diffusers
import torch

from wmjax.nn.vae import LAYOUTS  # SD 1.x / SDXL (4 latent channels), SD3 (16, no quant convs)


def save_random_vae(path, layout: str, seed: int = 0, widths=(32, 64), layers_per_block=2,
                    norm_num_groups=8):
  """A small random-weight diffusers AutoencoderKL saved with save_pretrained."""
  torch.manual_seed(seed)
  vae = diffusers.AutoencoderKL(
      block_out_channels=widths, down_block_types=("DownEncoderBlock2D",) * len(widths),
      up_block_types=("UpDecoderBlock2D",) * len(widths), layers_per_block=layers_per_block,
      norm_num_groups=norm_num_groups, **LAYOUTS[layout])
  with torch.no_grad():  # move every weight away from its initialisation (zero biases etc.)
    for p in vae.parameters():
      p.add_(0.05 * torch.randn_like(p))
  vae.save_pretrained(str(path))
  return vae
