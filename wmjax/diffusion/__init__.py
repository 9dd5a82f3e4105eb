"""Noise schedules, forward processes and objectives, samplers and scheduling matrices."""

from wmjax.diffusion.objectives import (FlowMatching, GaussianDiffusion, LevelSampling, Process,
                                        diffusion_loss, make_process, masked_loss_sum, Regression,
                                        training_levels, training_noise)
from wmjax.diffusion.sampling import (SamplerConfig, classifier_free_guidance, context_inputs,
                                      ddim_step, euler_step, sample_window, sampler_step,
                                      scheduling_matrix, window_denoiser)
from wmjax.diffusion.schedules import alphas_cumprod, make_betas

__all__ = [
    "FlowMatching", "GaussianDiffusion", "LevelSampling", "Process", "SamplerConfig", "alphas_cumprod",
    "classifier_free_guidance", "context_inputs", "ddim_step", "diffusion_loss", "euler_step",
    "make_betas", "make_process", "masked_loss_sum", "Regression", "sample_window", "sampler_step",
    "scheduling_matrix", "training_levels", "training_noise", "window_denoiser",
]
