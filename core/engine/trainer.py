"""One optimisation step of the distillation (the paper's §3.2): pick a frame; sample N
stratified probe pixels; place balls in front of the scene depth there; render ONLY the ball
pixels under the current field (queried at the ball centre for each reflected direction, at
the frame's time); composite into the linear frame; tone map at ev; ask the prior for a
stop-gradient pseudo-target; masked L2 (saturation hinge) + perceptual loss; one Adam step
with the scheduled learning rate and gradient clipping.

With radiance supervision (`use_envmaps`, core.engine.radiance) a step instead asks the prior
for HDR env maps at a few probes of the frame and fits the field's log radiance at many
random directions; the paper's ball loop stays the path of priors that only paint balls."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from core.capture.base import Capture
from core.chrome_ball import ball_reflection_rays, composite, composite_depth, place_probe, render_balls
from core.conventions import tonemap, tonemap_unclipped
from core.engine.config import DistillConfig
from core.engine.free_space import FreeSpaceSampler
from core.engine.losses import PerceptualLoss, masked_l2
from core.engine.probes import sample_probes
from core.engine.progress import StageTimer
from core.engine.radiance import bright_directions, radiance_loss, random_directions, supervision_probes, targets_at
from core.fields import LightField
from core.priors.base import Prior, PriorRequest, ProbeGeometry


@dataclass
class Trainer:
    """The state one optimisation step needs; `step(k)` runs step k and returns its loss."""

    capture: Capture  # on CPU: probe sampling and geometry are small, sequential work
    frames_lin: torch.Tensor  # [T, H, W, 3] ball-free background radiance (Capture.linear: no clip boost), on `device`
    depth: torch.Tensor  # [T, H, W] capture.depth on `device`
    prior: Prior
    field: LightField
    opt: torch.optim.Optimizer
    cfg: DistillConfig
    gen: torch.Generator
    perceptual: PerceptualLoss
    timings: StageTimer
    device: torch.device
    use_envmaps: bool = False  # radiance supervision (the prior answers env maps)
    floors: list[float] | None = None  # per-frame log floors of the radiance loss
    # [H*W, 3] camera-frame pixel rays when the camera probe is fitted to view radiance
    view_rays: torch.Tensor | None = None
    free_space: FreeSpaceSampler | None = None  # draws the probes off the camera rays (priors that answer anywhere)

    def step(self, step: int) -> float:
        if self.use_envmaps:
            return self.radiance_step(step)
        capture, cfg, gen, timings, field = self.capture, self.cfg, self.gen, self.timings, self.field
        i = int(torch.randint(capture.num_frames, (1,), generator=gen))
        # the prior sees the composite as the camera took the frame: its stated exposure plus the step's
        frame_ev = float(capture.frame_ev[i])
        ev = cfg.ev_at(step) + frame_ev
        tau_min = cfg.tau_min_at(step)
        tau = float(tau_min + (cfg.tau_max - tau_min) * torch.rand(1, generator=gen, dtype=torch.float64))
        cam = capture.camera(i)
        t = float(capture.times[i])

        with timings("probe_geometry"):
            pixels, depths = sample_probes(capture, i, cfg, gen)
            placed = [
                place_probe(cam, pixels[n], float(depths[n]), cfg.ball_diameter_fraction) for n in range(cfg.n_probes)
            ]
            centers = torch.stack([c for c, _ in placed])
            radii = torch.tensor([r for _, r in placed], dtype=torch.float32)
            rays = ball_reflection_rays(cam, centers, radii, supersample=cfg.supersample)

        with timings("field_render"):
            dev = self.device
            centers_dev = centers.to(dev)
            t_probes = torch.full((centers.shape[0],), t, device=dev)

            def radiance(directions: torch.Tensor, ball_index: torch.Tensor) -> torch.Tensor:
                # per-probe work (trunk, encodings of x and t) once per ball, not per ball sample
                return field.probe_radiance(centers_dev, t_probes, ball_index.to(dev), directions.to(dev))

            layer = render_balls(cam, centers, radii, radiance, rays=rays)
            comp = composite(self.frames_lin[i], layer)
            pred = tonemap_unclipped(comp, ev).permute(2, 0, 1)
            image = tonemap(comp.detach(), ev).permute(2, 0, 1)
            mask = layer.total_coverage.detach()

        with timings("prior"):
            pd = self.prior.device
            probes = ProbeGeometry(centers, radii, pixels.float(), cam, i, t)
            request = PriorRequest(
                image=image.to(pd), ball_masks=layer.coverage.detach().to(pd),
                depth=composite_depth(self.depth[i], layer).to(pd), ev=ev, tau=tau, steps=cfg.steps_for_tau(tau),
                guidance_scale=cfg.guidance_scale, probes=probes, generator=gen, frame_ev=frame_ev,
                extras={"frame_linear": self.frames_lin[i].to(pd), "ball_rays": rays,
                        "depth_background": self.depth[i].to(pd)},
            )
            target = self.prior(request).detach().to(device=pred.device, dtype=pred.dtype)
            target = torch.nan_to_num(target, nan=0.0).clamp(0.0, 1.0)

        with timings("optimisation"):
            pred, target, mask = crop_to_mask(pred, target, mask, pad=4)
            loss = cfg.l2_weight * masked_l2(pred, target, mask)
            if cfg.perceptual_weight > 0:
                loss = loss + cfg.perceptual_weight * self.perceptual(pred.clamp(0, 1), target, mask)
            return self._optimise(step, loss)

    def radiance_step(self, step: int) -> float:
        """One step of radiance supervision: `envmap_frames_per_step` frames, each with its
        probes; the prior's env maps there; a log-radiance fit at `envmap_directions` directions
        per probe (uniform, plus a share drawn by the target's luminance), and, when the prior
        gives view radiance, `envmap_view_directions` of the frame's pixel rays at the camera
        centre (the last probe) fitted to those pixels."""
        capture, cfg, gen, timings, field = self.capture, self.cfg, self.gen, self.timings, self.field
        frames = torch.randint(capture.num_frames, (cfg.envmap_frames_per_step,), generator=gen).tolist()
        centers, times, targets, dirs, floors, index = [], [], [], [], [], []
        n_seen = 0
        for i in frames:
            t = float(capture.times[i])
            with timings("probe_geometry"):
                c = supervision_probes(capture, i, cfg, gen, self.free_space)
            with timings("prior"):
                maps = self.prior.envmaps(c.to(self.prior.device), t, cfg.envmap_height).detach().float().cpu()
                maps = torch.nan_to_num(maps, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
                n, k = c.shape[0], cfg.envmap_directions
                k_bright = round(k * cfg.envmap_bright_fraction)
                d = random_directions(n * (k - k_bright), gen).reshape(n, k - k_bright, 3)
                if k_bright:
                    d = torch.cat((d, bright_directions(maps, k_bright, gen)), dim=1)
                targets.append(targets_at(maps, d).reshape(-1, 3))
                dirs.append(d.reshape(-1, 3))
                index.append(torch.arange(n_seen, n_seen + n).repeat_interleave(k))
                rows = n * k
                if self.view_rays is not None:
                    pick = torch.randint(self.view_rays.shape[0], (cfg.envmap_view_directions,), generator=gen)
                    dirs.append(self.view_rays[pick] @ capture.poses[i, :3, :3].T.float())  # to world
                    seen = self.prior.view_radiance(i).detach().reshape(-1, 3)[pick.to(self.prior.device)].float().cpu()
                    targets.append(torch.nan_to_num(seen, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0))
                    index.append(torch.full((pick.shape[0],), n_seen + n - 1))  # the camera centre: the last probe
                    rows += pick.shape[0]
            centers.append(c)
            times.append(torch.full((n,), t))
            floors.append(torch.full((rows, 1), self.floors[i]))
            n_seen += n
        with timings("field_render"):
            dev = self.device
            pred = field.probe_radiance(torch.cat(centers).to(dev), torch.cat(times).to(dev), torch.cat(index).to(dev),
                                        torch.cat(dirs).to(dev))
        with timings("optimisation"):
            loss = radiance_loss(
                pred, torch.cat(targets).to(dev), torch.cat(floors).to(dev), cfg.linear_weight, cfg.chroma_weight
            )
            return self._optimise(step, loss)

    def _optimise(self, step: int, loss: torch.Tensor) -> float:
        """Add the time-code TV penalty, then one clipped Adam step at the scheduled rate."""
        cfg, field = self.cfg, self.field
        tv = field.time_variation()
        if tv is not None and cfg.time_tv_weight > 0:
            loss = loss + cfg.time_tv_weight * tv
        for g in self.opt.param_groups:
            g["lr"] = cfg.lr_at(step) * g.get("lr_scale", 1.0)
        self.opt.zero_grad(set_to_none=True)
        if torch.isfinite(loss):
            loss.backward()
            torch.nn.utils.clip_grad_norm_(field.parameters(), cfg.grad_clip)
            self.opt.step()
        return float(loss.detach())


def crop_to_mask(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, pad: int):
    """Crop [3,H,W] images and the [H,W] mask to the balls' bounding box plus `pad` pixels
    (the SSIM window's reach), so the loss never touches pixels no ball covers."""
    rows = torch.nonzero(mask.amax(1) > 0)
    cols = torch.nonzero(mask.amax(0) > 0)
    if rows.numel() == 0:
        return pred, target, mask
    r0, r1 = max(int(rows[0]) - pad, 0), min(int(rows[-1]) + pad + 1, mask.shape[0])
    c0, c1 = max(int(cols[0]) - pad, 0), min(int(cols[-1]) + pad + 1, mask.shape[1])
    return pred[:, r0:r1, c0:c1], target[:, r0:r1, c0:c1], mask[r0:r1, c0:c1]
