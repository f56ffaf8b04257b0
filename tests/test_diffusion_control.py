"""Canvas geometry per profile and the ControlNet encodings (no network models involved)."""
from __future__ import annotations

import torch

from core.camera import Camera, Intrinsics, identity_pose
from core.chrome_ball import place_probe
from core.priors.base import ProbeGeometry
from core.priors.diffusion.canvas import make_canvas
from core.priors.diffusion.control import ControlInputs, control_image, normal_map


def test_letterbox_keeps_aspect_pads_black_and_round_trips():
    c = make_canvas("letterbox", (30, 60), (64, 64), 64)
    assert c.size == (64, 64) and c.box == (16, 0, 32, 64)
    x = torch.linspace(0.1, 0.9, 60).expand(1, 3, 30, 60).clone()  # smooth: survives the resampling
    m = c.to_model(x)
    assert float(m[..., :16, :].abs().max()) == 0.0 and float(m[..., 48:, :].abs().max()) == 0.0
    back = c.to_frame(m)
    assert back.shape == x.shape and float((back - x).abs().max()) < 0.02
    mask = c.mask_to_model(torch.zeros(2, 30, 60).index_fill_(1, torch.tensor([0]), 1.0))
    assert mask.shape == (2, 64, 64) and float(mask[:, :16].sum()) == 0.0 and float(mask[:, 16].min()) == 1.0
    s = make_canvas("squash", (30, 60), (64, 64), 64)
    assert s.size == (64, 64) and s.full


def _plane_and_ball(h=24, w=32):
    cam = Camera(Intrinsics.from_hfov(w, h, 60.0), identity_pose())
    depth = torch.full((h, w), 3.0)
    centre, r = place_probe(cam, torch.tensor([w / 2, h / 2], dtype=torch.float64), 1.5, 0.25)
    yy, xx = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    mask = (((xx - w / 2) ** 2 + (yy - h / 2) ** 2) < 9.0).float()[None]
    probes = ProbeGeometry(
        centre[None].float(), torch.tensor([r], dtype=torch.float32), torch.tensor([[w / 2, h / 2]]), cam, 0, 0.0
    )
    return ControlInputs(depth, depth, mask, probes), cam


def test_normals_follow_diffusionlight_convention():
    inputs, _ = _plane_and_ball()
    n = normal_map(inputs)  # [3, H, W] in [0, 1]
    corner = n[:, 2, 2]
    torch.testing.assert_close(corner, torch.tensor([0.5, 0.5, 1.0]), atol=1e-4, rtol=0)  # a wall facing the camera
    centre = n[:, 12, 16]
    assert float(centre[2]) > 0.95  # the ball's front faces the viewer
    left, right = n[:, 12, 14], n[:, 12, 18]
    assert float(left[0]) > 0.5 > float(right[0])  # x points towards the image's left (DiffusionLight's flip)
    top, bottom = n[:, 10, 16], n[:, 14, 16]
    assert float(top[1]) > 0.5 > float(bottom[1])  # y up


def test_diffusionlight_depth_fills_the_ball_with_nearest():
    inputs, _ = _plane_and_ball()
    canvas = make_canvas("keep_aspect", (24, 32), (24, 32), 8)
    ctrl = control_image("diffusionlight_nearest", inputs, canvas, "cpu")
    assert float(ctrl[0][inputs.ball_masks[0] > 0].min()) == 1.0
    assert float(ctrl[0][inputs.ball_masks[0] == 0].max()) == 0.5  # a flat scene: no structure to convey
