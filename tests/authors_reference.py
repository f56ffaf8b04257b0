"""Test-only reference of the authors' released denoising step, written here from reading
ORionTMT/Sig25_4DLighting (no code copied). It is deliberately structured like their code
and built on diffusers' own pipeline pieces (StableDiffusionControlNetInpaintPipeline's
`_encode_vae_image`, `mask_processor`, `control_image_processor`, `encode_prompt`, diffusers'
`rescale_noise_cfg`), so it shares no code with core/priors/diffusion/seed.py:

* `reference_control`   <- SDS/multiball_sds.py `prepare_depth_control_image_withdepth` +
                            `project_multiball` (per-ball fill, uint8 round trip, PIL -> processor)
* `reference_prompts`   <- Lighting/sds_common.py `get_interpolated_prompt_embeds` and the
                            negative branch of `pipe_sds.encode_prompt` in `sds_loop`
* `reference_target`    <- Lighting/sds_utils.py `PipeSDS21.loss_sds_image` (image space,
                            multistep) with `get_sub_timesteps`, `encode_mask`,
                            Lighting/pipeline_utils.py `custom_prepare_mask_latents`
* `_noise_predict`      <- Lighting/sds_utils.py `PipeSDS21.noise_predict`
* `_ddim_sds_step`      <- Lighting/sds_scheduler.py `DDIMSchedulerSDS.step` (eta = 0)

One substitution: their `noise = torch.randn_like(image_latents)` draws from torch's global
RNG; here it is drawn from the same generator as the VAE samples, at the same point.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image


def reference_pipeline(components):
    from diffusers import DDIMScheduler, StableDiffusionControlNetInpaintPipeline

    c = components
    pipe = StableDiffusionControlNetInpaintPipeline(
        vae=c.vae, text_encoder=c.text_encoder, tokenizer=c.tokenizer, unet=c.unet, controlnet=c.controlnet,
        scheduler=DDIMScheduler.from_config(c.scheduler.config), safety_checker=None, feature_extractor=None,
        requires_safety_checker=False,
    )
    pipe.set_progress_bar_config(disable=True)
    return pipe


def reference_control(pipe, disparity: torch.Tensor, ball_masks: list[np.ndarray], ball_z: list[float]) -> torch.Tensor:
    """disparity [H, W] (what DPT would give), boolean masks [H, W] per ball, z per ball (their units)."""
    depth_map = disparity[None, None].float()
    h, w = disparity.shape
    final = None
    for mask, z in zip(ball_masks, ball_z):
        d = (depth_map - torch.amin(depth_map, dim=[1, 2, 3], keepdim=True))
        d = d / (
            torch.amax(depth_map, dim=[1, 2, 3], keepdim=True) - torch.amin(depth_map, dim=[1, 2, 3], keepdim=True)
        )
        d = d.squeeze(0).permute(1, 2, 0).repeat(1, 1, 3)
        fill = torch.full((h, w, 3), float(np.power(1.0 / z, 1 / 2.4)))
        mb = torch.tensor(mask.astype(bool))
        d[mb] = fill[mb]
        ctrl = np.array(Image.fromarray((d.numpy() * 255).astype(np.uint8)))
        if final is None:
            final = ctrl
        else:
            m = np.repeat(mask.astype(np.float32)[..., None], 3, axis=-1)
            final = final * (1 - m) + ctrl * m
    image = Image.fromarray(final.astype(np.uint8))
    return pipe.control_image_processor.preprocess(image, height=h, width=w).float()


def reference_prompts(pipe, prompt: str, prompt_dark: str, ev: float, max_negative_ev: float):
    device = pipe.text_encoder.device
    normal = pipe.encode_prompt(prompt, device, num_images_per_prompt=1, do_classifier_free_guidance=True)[0]
    dark = pipe.encode_prompt(prompt_dark, device, num_images_per_prompt=1, do_classifier_free_guidance=True)[0]
    t = ev / max_negative_ev
    _, negative = pipe.encode_prompt(prompt=prompt, negative_prompt="", device=device, num_images_per_prompt=1,
                                     do_classifier_free_guidance=True)
    return normal + t * (dark - normal), negative


def _ddim_sds_step(scheduler, model_output, timestep, sample, prev_timestep):
    alpha_prod_t = scheduler.alphas_cumprod[timestep]
    alpha_prod_t_prev = scheduler.alphas_cumprod[prev_timestep] if prev_timestep >= 0 else scheduler.final_alpha_cumprod
    beta_prod_t = 1 - alpha_prod_t
    pred_original_sample = (sample - beta_prod_t ** 0.5 * model_output) / alpha_prod_t ** 0.5  # epsilon
    if scheduler.config.clip_sample:
        pred_original_sample = pred_original_sample.clamp(
            -scheduler.config.clip_sample_range, scheduler.config.clip_sample_range
        )
    variance = scheduler._get_variance(timestep, prev_timestep)
    std_dev_t = 0.0 * variance ** 0.5
    pred_sample_direction = (1 - alpha_prod_t_prev - std_dev_t ** 2) ** 0.5 * model_output
    return alpha_prod_t_prev ** 0.5 * pred_original_sample + pred_sample_direction


def _prepare_mask_latents(pipe, mask, masked_image, height, width, generator):
    mask = F.interpolate(mask, size=(height // pipe.vae_scale_factor, width // pipe.vae_scale_factor),
                         mode="bilinear", align_corners=False)
    masked_image_latents = pipe._encode_vae_image(masked_image, generator=generator)
    return mask, masked_image_latents


def _noise_predict(pipe, latents, mask, masked_image_latents, t, prompt_embeds, negative_prompt_embeds,
                   guidance_scale, control_image, controlnet_conditioning_scale, log):
    from diffusers.pipelines.stable_diffusion.pipeline_stable_diffusion import rescale_noise_cfg

    do_cfg = guidance_scale > 1.0
    latent_model_input = torch.cat([latents] * 2) if do_cfg else latents
    latent_model_input = pipe.scheduler.scale_model_input(latent_model_input, t)
    if do_cfg:
        prompt_embeds = torch.cat([negative_prompt_embeds, prompt_embeds])
    controlnet_prompt_embeds = prompt_embeds.expand(latent_model_input.shape[0], -1, -1)
    log["controlnet_input"].append(control_image)
    down, mid = pipe.controlnet(latent_model_input, t, encoder_hidden_states=controlnet_prompt_embeds,
                                controlnet_cond=control_image, conditioning_scale=controlnet_conditioning_scale,
                                guess_mode=False, return_dict=False)
    if do_cfg:
        mask = torch.cat([mask] * 2)
        masked_image_latents = torch.cat([masked_image_latents] * 2)
    latent_model_input = torch.cat([latent_model_input, mask, masked_image_latents], dim=1)
    noise_pred = pipe.unet(
        latent_model_input,
        t,
        encoder_hidden_states=prompt_embeds,
        down_block_additional_residuals=down,
        mid_block_additional_residual=mid,
        return_dict=False,
    )[0]
    if do_cfg:
        uncond, text = noise_pred.chunk(2)
        noise_pred = uncond + guidance_scale * (text - uncond)
        noise_pred = rescale_noise_cfg(noise_pred, text, guidance_rescale=1.0)
    return noise_pred


@torch.no_grad()
def reference_target(pipe, image, mask, clean, control, prompt_embeds, negative_prompt_embeds, tau, guidance_scale,
                     control_scale, generator):
    """Their `sds_loop` -> `loss_sds_image(queried_image, mask, input, timestep, multistep=round(10 t))`.

    image / clean: [1, 3, H, W] in [-1, 1]; mask: [1, H, W] binary; control: [1, 3, H, W] in [0, 1].
    Returns (image_pred, log) with the per-step ControlNet inputs, CFG outputs and latents."""
    from diffusers.utils.torch_utils import randn_tensor

    log = {"controlnet_input": [], "noise_pred": [], "latents": []}
    timestep = int(pipe.scheduler.config.num_train_timesteps * tau)
    multistep = round(tau * 10)
    height, width = image.shape[-2:]

    def get_sub_timesteps(timestep, n_steps):
        timestep_idx = (pipe.scheduler.timesteps == timestep).nonzero(as_tuple=True)[0].item()
        timestep_min_idx = len(pipe.scheduler.timesteps) - 1
        assert timestep_min_idx - timestep_idx >= n_steps
        idx = torch.linspace(timestep_idx, timestep_min_idx, n_steps + 1).round().int()
        return pipe.scheduler.timesteps[idx]

    image_latents = pipe._encode_vae_image(image, generator=generator)
    m = pipe.mask_processor.preprocess(mask)  # encode_mask
    latent_mask = F.interpolate(m, size=(height // pipe.vae_scale_factor, width // pipe.vae_scale_factor),
                                mode="bilinear", align_corners=False)
    noise = randn_tensor(image_latents.shape, generator=generator, dtype=image_latents.dtype)  # their randn_like
    noisy_latents = pipe.scheduler.add_noise(image_latents, noise, torch.tensor([timestep]))
    if not multistep > 1:
        multistep = 5
    timestep_list = get_sub_timesteps(timestep, multistep)
    ctrl = torch.cat([control] * 2, dim=0) if guidance_scale > 1.0 else control
    cur_mask = mask
    for i in range(multistep):
        t, prev = timestep_list[i], timestep_list[i + 1]
        cur_mask = cur_mask.squeeze(1)
        cur_mask, masked_image_latents = _prepare_mask_latents(
            pipe, cur_mask.unsqueeze(0), clean, height, width, generator
        )
        cur_mask = cur_mask[:, :1, :, :]
        noise_pred = _noise_predict(pipe, noisy_latents, cur_mask, masked_image_latents, t, prompt_embeds,
                                    negative_prompt_embeds, guidance_scale, ctrl, control_scale, log)
        noisy_latents = _ddim_sds_step(pipe.scheduler, noise_pred, t, noisy_latents, prev)
        if i < multistep - 1:
            image_latents_noised = pipe.scheduler.add_noise(image_latents, noise, torch.tensor([prev]))
            noisy_latents = (1 - latent_mask) * image_latents_noised + latent_mask * noisy_latents
        log["noise_pred"].append(noise_pred)
        log["latents"].append(noisy_latents)
    image_pred = pipe.vae.decode(noisy_latents / pipe.vae.config.scaling_factor, return_dict=False)[0]
    image_mask = mask
    image_pred = (1 - image_mask) * image + image_mask * image_pred
    log["timesteps"] = [int(t) for t in timestep_list]
    return image_pred, log
