"""Exposure conditioning (paper §3.1): the text embedding slides between two prompts.

    zeta(ev) = zeta_max + (ev / ev_min) * (zeta_min - zeta_max),   ev in [ev_min, 0]

zeta_max embeds the "mirrored chrome ball" prompt (EV 0), zeta_min the "black dark" one
(ev_min). EVs outside [ev_min, 0] are clamped: the model never saw them in training, and
extrapolating an embedding leaves the text manifold. Both the per-token embedding the UNet
cross-attends to and the pooled embedding are interpolated. The classifier-free-guidance
branch uses the embedding of the card's negative prompt: empty for the paper's model
(what exposure dropout trains towards), "matte, diffuse, flat, dull" for DiffusionLight.

SDXL (two text encoders, as diffusers' StableDiffusionXLPipeline.encode_prompt): the tokens
are both encoders' penultimate hidden states side by side, the pooled embedding is the
second encoder's projection; an empty negative prompt is all zeros
(`force_zeros_for_empty_prompt`, SDXL's default).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ExposureEmbedding:
    tokens: torch.Tensor  # [B, L, D] what the UNet / ControlNet cross-attend to
    pooled: torch.Tensor | None  # [B, P] pooled (or projected) embedding, if the encoder has one

    def repeat(self, n: int) -> "ExposureEmbedding":
        return ExposureEmbedding(
            self.tokens.repeat(n, 1, 1), None if self.pooled is None else self.pooled.repeat(n, 1)
        )

    @staticmethod
    def cat(items: list["ExposureEmbedding"]) -> "ExposureEmbedding":
        pooled = None if items[0].pooled is None else torch.cat([e.pooled for e in items])
        return ExposureEmbedding(torch.cat([e.tokens for e in items]), pooled)


def exposure_weight(ev: torch.Tensor | float, ev_min: float) -> torch.Tensor:
    """ev / ev_min after clamping ev to [ev_min, 0]: 0 at EV 0, 1 at ev_min."""
    ev = torch.as_tensor(ev, dtype=torch.float32)
    ev = torch.nan_to_num(ev, nan=0.0).clamp(min=ev_min, max=0.0)
    return ev / ev_min


def interpolate(weight: torch.Tensor, at_max: torch.Tensor, at_min: torch.Tensor) -> torch.Tensor:
    """at_max + w (at_min - at_max), with one weight per batch item ([B] against [1, ...])."""
    w = weight.to(at_max.dtype).to(at_max.device).reshape(-1, *([1] * (at_max.dim() - 1)))
    return at_max + w * (at_min - at_max)


class ExposureConditioner:
    """Encodes the two anchor prompts and the null prompt once, then answers zeta(ev) cheaply."""

    def __init__(self, text_encoder, tokenizer, prompt_max: str, prompt_min: str, ev_min: float,
                 negative_prompt: str = "", text_encoder_2=None, tokenizer_2=None):
        self.ev_min = float(ev_min)
        device = next(text_encoder.parameters()).device
        if text_encoder_2 is None:
            def encode(p):
                return _encode(text_encoder, tokenizer, p, device)
        else:
            def encode(p):
                return _encode_sdxl((text_encoder, text_encoder_2), (tokenizer, tokenizer_2), p, device)
        self.max, self.min = encode(prompt_max), encode(prompt_min)
        self.null = encode(negative_prompt)
        if text_encoder_2 is not None and negative_prompt == "":
            self.null = ExposureEmbedding(torch.zeros_like(self.null.tokens), torch.zeros_like(self.null.pooled))

    def __call__(self, evs: torch.Tensor | float | list[float]) -> ExposureEmbedding:
        """zeta for each EV in `evs` (a scalar gives a batch of one)."""
        w = exposure_weight(evs, self.ev_min).reshape(-1)
        pooled = None if self.max.pooled is None else interpolate(w, self.max.pooled, self.min.pooled)
        return ExposureEmbedding(interpolate(w, self.max.tokens, self.min.tokens), pooled)

    def null_embedding(self, batch: int = 1) -> ExposureEmbedding:
        return self.null.repeat(batch)


@torch.no_grad()
def _encode(text_encoder, tokenizer, prompt: str, device) -> ExposureEmbedding:
    ids = tokenizer(
        prompt, padding="max_length", max_length=tokenizer.model_max_length, truncation=True, return_tensors="pt"
    ).input_ids.to(device)
    out = text_encoder(ids)
    pooled = getattr(out, "text_embeds", None)  # CLIPTextModelWithProjection
    if pooled is None:
        pooled = getattr(out, "pooler_output", None)
    return ExposureEmbedding(out.last_hidden_state.detach(), None if pooled is None else pooled.detach())


@torch.no_grad()
def _encode_sdxl(encoders, tokenizers, prompt: str, device) -> ExposureEmbedding:
    tokens, pooled = [], None
    for enc, tok in zip(encoders, tokenizers):
        ids = tok(prompt, padding="max_length", max_length=tok.model_max_length, truncation=True,
                  return_tensors="pt").input_ids.to(device)
        out = enc(ids, output_hidden_states=True)
        tokens.append(out.hidden_states[-2])
        pooled = out[0]  # the last encoder's projection (CLIPTextModelWithProjection.text_embeds)
    return ExposureEmbedding(torch.cat(tokens, dim=-1).detach(), pooled.detach())
