"""IRASim's PyTorch model against its wmjax import: one denoiser call and one sampled clip.

For each size and variant, IRASim's ``models/irasim.py`` (from the user's checkout, ``--irasim``)
is built with random weights (its own initialisation, then every tensor redrawn so that the
zero-initialised adaLN and output layers do not hide a wrong mapping), converted with
:func:`wmjax.checkpoints.irasim.from_irasim` under the config ``wmjax import irasim`` writes, and
both models get the same inputs in float32:

* one call: a noisy RT-1-shaped latent window, one timestep per sample, 15 actions;
* one sampled clip: ``--sampler`` (DDIM with eta 0 by default; ``pndm_prk`` is the PNDM with
  its Runge-Kutta warm-up that IRASim evaluates with) from the same noise with the first frame as
  clean context, IRASim's pipeline loop (``sample/pipeline_trajectory2videogen.py``: the context
  frame is put back after every step and the model gets one timestep for every frame) with
  diffusers' scheduler at ``timestep_spacing='trailing'`` (DDIM: timesteps 999, 979, ..., 19 then
  clean, the levels wmjax visits) against :func:`wmjax.diffusion.sample_window`.

Max relative error: ``max |a - b| / max |b|`` over the output (IRASim's the reference).

  python experiments/irasim_parity/parity.py --irasim ~/IRASim [--sizes S,XL] [--steps 10] \
      [--sampler ddim|pndm|pndm_prk|dpm_solver++] [--latent 32,40]

``--latent`` shrinks the latent frames (RT-1's are 32x40) to make XL/2 affordable on a CPU; the
weights are the same shapes at any frame size.

IRASim's model needs ``timm`` and ``einops``; its loop needs ``diffusers``.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from wmjax.checkpoints import irasim as importer  # noqa: E402
from wmjax.diffusion import sample_window  # noqa: E402
from wmjax.model import WorldModel  # noqa: E402

VARIANTS = {"frame_ada": 3, "video_ada": 5}  # IRASim's `extras`


def irasim_module(checkout: str):
  """``models/irasim.py`` of an IRASim checkout, imported on its own (``models/__init__`` pulls
  in the baselines)."""
  path = os.path.join(os.path.expanduser(checkout), "models", "irasim.py")
  spec = importlib.util.spec_from_file_location("irasim_models", path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def build_irasim(module, size: str, variant: str, frame_shape, seed: int):
  """IRASim-``size``/2 for RT-1 (evaluation config: learn_sigma False, final_frame_ada False),
  every parameter redrawn from N(0, 0.02^2) (biases too)."""
  import torch
  args = argparse.Namespace(dataset="rt1", final_frame_ada=False)
  model = module.IRASim_models[f"IRASim-{size}/2"](
      input_size=list(frame_shape[:2]), num_frames=16, learn_sigma=False,
      extras=VARIANTS[variant], attention_mode="math", args=args)
  generator = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for p in model.parameters():
      if p.requires_grad:
        p.copy_(0.02 * torch.randn(p.shape, generator=generator))
  return model.eval()


def relative_error(a: np.ndarray, reference: np.ndarray) -> float:
  return float(np.abs(a - reference).max() / np.abs(reference).max())


def to_wmjax_frames(x):
  """``[B, F, C, H, W]`` torch -> ``[B, F, H, W, C]`` jax."""
  return jnp.asarray(x.numpy().transpose(0, 1, 3, 4, 2))


def diffusers_scheduler(sampler: str, steps: int):
  """diffusers' scheduler for a wmjax ``sampler`` on IRASim's linear betas, at the levels wmjax
  visits (``timestep_spacing='trailing'``, clean end point)."""
  import diffusers
  common = dict(num_train_timesteps=1000, beta_start=1e-4, beta_end=0.02, beta_schedule="linear",
                timestep_spacing="trailing", prediction_type="epsilon")
  if sampler == "ddim":
    scheduler = diffusers.DDIMScheduler(clip_sample=False, set_alpha_to_one=True, **common)
  elif sampler in ("pndm", "pndm_prk"):
    scheduler = diffusers.PNDMScheduler(skip_prk_steps=sampler == "pndm", set_alpha_to_one=True,
                                        **common)
  elif sampler == "dpm_solver++":
    scheduler = diffusers.DPMSolverMultistepScheduler(
        algorithm_type="dpmsolver++", solver_order=2, solver_type="midpoint",
        lower_order_final=True, final_sigmas_type="zero", **common)
  else:
    raise SystemExit(f"--sampler must be ddim, pndm, pndm_prk or dpm_solver++, got {sampler!r}")
  scheduler.set_timesteps(steps)
  return scheduler


def irasim_sample(model, scheduler, noise, context, actions):
  """IRASim's pipeline loop: ``noise [B, F, C, H, W]``, clean ``context [B, 1, C, H, W]``."""
  import torch
  latents = torch.cat([context, noise[:, 1:]], dim=1)
  with torch.no_grad():
    for t in scheduler.timesteps:
      out = model(latents, t[None].expand(latents.shape[0]).float(), actions=actions)
      latents = scheduler.step(out, t, latents, return_dict=False)[0]
      latents = torch.cat([context, latents[:, 1:]], dim=1)
  return latents


def compare(module, size: str, variant: str, sampler: str, steps: int, seed: int,
            latent) -> dict:
  import torch
  config = importer.import_config(size, "rt1", variant)
  config.sampling.sampler, config.sampling.num_steps = sampler, steps
  config.frame_shape = tuple(latent) + (config.frame_shape[2],)
  world = WorldModel.from_config(config)
  frame_shape = tuple(config.frame_shape)
  torch_model = build_irasim(module, size, variant, frame_shape, seed)
  state = {k: v.numpy() for k, v in torch_model.state_dict().items()}
  params = importer.from_irasim(state, world.network, frame_shape)

  generator = torch.Generator().manual_seed(seed + 1)
  h, w, c = frame_shape
  x = torch.randn((1, 16, c, h, w), generator=generator)
  actions = torch.randn((1, 15, 7), generator=generator)
  t = torch.tensor([500.0])
  start = time.time()
  with torch.no_grad():
    reference = torch_model(x, t, actions=actions).numpy().transpose(0, 1, 3, 4, 2)
  ours = world.network.apply(params, to_wmjax_frames(x), jnp.full((1, 16), 500.0),
                             jnp.asarray(actions.numpy()))
  call_error = relative_error(np.asarray(ours), reference)

  scheduler = diffusers_scheduler(sampler, steps)
  context = torch.randn((1, 1, c, h, w), generator=generator)
  noise = torch.randn((1, 16, c, h, w), generator=generator)
  reference_clip = irasim_sample(torch_model, scheduler, noise, context, actions)
  reference_clip = reference_clip[:, 1:].numpy().transpose(0, 1, 3, 4, 2)
  denoise = world.new_frame_denoiser(params, to_wmjax_frames(context), jnp.asarray(actions.numpy()),
                                     jnp.ones((1, 15), bool))
  clip = sample_window(jax.jit(denoise), world.process, world.sampler,
                       to_wmjax_frames(noise[:, 1:]), jax.random.key(0))
  return dict(size=size, variant=variant, call=call_error,
              clip=relative_error(np.asarray(clip), reference_clip), steps=steps,
              calls=len(scheduler.timesteps),
              seconds=time.time() - start)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--irasim", required=True, help="an IRASim checkout (bytedance/IRASim)")
  parser.add_argument("--sizes", default="S,XL")
  parser.add_argument("--variants", default="frame_ada,video_ada")
  parser.add_argument("--sampler", default="ddim",
                      help="ddim, pndm, pndm_prk (IRASim's evaluation sampler) or dpm_solver++")
  parser.add_argument("--steps", type=int, default=10, help="sampler steps of the sampled clip")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--latent", default="32,40", help="latent frame size H,W")
  args = parser.parse_args()
  latent = tuple(int(n) for n in args.latent.split(","))
  sys.path.insert(0, os.path.expanduser(args.irasim))
  module = irasim_module(args.irasim)
  print(f"latent frames {latent}, seed {args.seed}")
  print("| size | variant | one call: max rel. error | sampled clip: max rel. error | sampler, "
        "steps (network calls) |")
  print("|---|---|---|---|---|")
  for size in args.sizes.split(","):
    for variant in args.variants.split(","):
      r = compare(module, size, variant, args.sampler, args.steps, args.seed, latent)
      print(f"| {r['size']}/2 | {r['variant']} | {r['call']:.2e} | {r['clip']:.2e} | "
            f"{args.sampler}, {r['steps']} ({r['calls']}) |", flush=True)
      print(f"<!-- {r['seconds']:.0f} s -->", file=sys.stderr, flush=True)


if __name__ == "__main__":
  main()
