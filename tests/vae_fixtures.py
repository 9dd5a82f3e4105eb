"""Small random-weight diffusers AutoencoderKL folders (needs torch and diffusers, test extra)."""

import diffusers
import torch

LAYOUTS = {
    # SD 1.x / SDXL: 4 latent channels, quant convs (SDXL scaling 0.13025)
    "sdxl": dict(latent_channels=4, scaling_factor=0.13025),
    # SD3: 16 latent channels, no quant convs, scaling 1.5305 and shift 0.0609
    "sd3": dict(latent_channels=16, scaling_factor=1.5305, shift_factor=0.0609,
                use_quant_conv=False, use_post_quant_conv=False),
}


def save_random_vae(path, layout: str, seed: int = 0, widths=(32, 64)):
  """A small random-weight diffusers AutoencoderKL saved with save_pretrained."""
  torch.manual_seed(seed)
  vae = diffusers.AutoencoderKL(
      block_out_channels=widths, down_block_types=("DownEncoderBlock2D",) * len(widths),
      up_block_types=("UpDecoderBlock2D",) * len(widths), layers_per_block=2, norm_num_groups=8,
      **LAYOUTS[layout])
  with torch.no_grad():  # move every weight away from its initialisation (zero biases etc.)
    for p in vae.parameters():
      p.add_(0.05 * torch.randn_like(p))
  vae.save_pretrained(str(path))
  return vae
