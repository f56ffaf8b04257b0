"""Do neighbouring frames agree where the capture says they overlap?

The field is fitted to the frames as the capture reads them, so re-rendering the frames from it
(core.engine.self_check) cannot see a misread the field could absorb: a field with a time input
explains frames from two rooms as a change of light, and one without explains a track that drifts
by blurring what it saw. Geometry can see it. Each frame's pixels are carried through its depth
and pose into the next frame. If the capture is read right, the next frame saw the same surfaces
there, and the ratio of the two frames is what changed in the light reaching them: an exposure
step (one factor for the frame) or a light switched on or off (a factor per surface that follows
the light's irradiance, smooth across the surface). A surface's texture, its albedo, is in both
frames and cancels. A misplaced view or another scene leaves texture in the ratio.

So the check compares the fine texture (the log image less its local mean over SMOOTH_PX pixels)
of the pair's log ratio with the fine texture of the frame itself: the reference, as for the field,
is the constant map, which predicts none of the frame's texture. A neighbour whose ratio holds as
much texture as the frame, beyond the noise two frames of one surface differ by (`frame_agreement`),
has not seen the same surfaces where the poses and depth put them: a track that turned the wrong
way, depth at the wrong scale, a cut to another scene. No threshold is learned; a pair with too
little overlap to say is not counted. What it cannot tell: a wrong exposure course (a factor per
frame, as an even dimming is), errors small enough that the ratio keeps less texture than the
frame, and frames with no texture above their noise (a blank wall, a flat rendered room).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from core.capture.base import Capture
from core.conventions import valid_depth_mask

MIN_OVERLAP = 16  # pixels of a pair that must land in the neighbour before it is judged
SMOOTH_PX = 5  # the local mean's window at the check's 24 rows: a fifth of the frame, finer is texture
_EPS = 1e-6


def _log_texture(linear: torch.Tensor) -> torch.Tensor:
    return torch.log(linear.clamp_min(_EPS)).mean(-1)


def fine_texture(image: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """|image - its local mean| [H, W] over the valid pixels (the mean over valid ones only)."""
    w = valid.double()[None, None]
    x = torch.where(valid, image.double(), torch.zeros_like(image, dtype=torch.float64))[None, None]
    pad = SMOOTH_PX // 2
    total = F.avg_pool2d(F.pad(x * w, (pad,) * 4), SMOOTH_PX, stride=1)
    weight = F.avg_pool2d(F.pad(w, (pad,) * 4), SMOOTH_PX, stride=1)
    return (x - total / weight.clamp_min(1e-12))[0, 0].abs()


def pair_residuals(capture: Capture, i: int, j: int, usable: torch.Tensor, log_tex: torch.Tensor
                   ) -> tuple[float, float] | None:
    """(the fine texture left in the log ratio of frame i to frame j carried onto it through depth and
    poses, the fine texture of frame i), medians over the overlap; None: too little overlap."""
    depth = capture.depth[i]
    keep = usable[i] & valid_depth_mask(depth)
    if int(keep.sum()) < MIN_OVERLAP:
        return None
    u, v, z = capture.camera(j).project(capture.camera(i).unproject(depth.double()))
    col, row = u.floor().long(), v.floor().long()
    inside = keep & (z > 0) & (col >= 0) & (col < capture.width) & (row >= 0) & (row < capture.height)
    col, row = col.clamp(0, capture.width - 1), row.clamp(0, capture.height - 1)
    inside &= usable[j][row, col]
    if int(inside.sum()) < MIN_OVERLAP:
        return None
    ratio = log_tex[i] - log_tex[j][row, col]
    neighbour = float(fine_texture(ratio, inside)[inside].median())
    constant = float(fine_texture(log_tex[i], inside)[inside].median())
    return neighbour, constant


def frame_agreement(capture: Capture, usable: torch.Tensor, linear: torch.Tensor) -> dict:
    """Consecutive frames compared through depth and poses (module docstring): the pairs checked,
    those whose ratio keeps the frame's texture beyond the noise floor, the floor, and the longest run
    of frames joined by agreeing pairs (a share of the frames).

    The floor is the texture the clip's best agreeing pair still leaves (sensor noise, compression,
    registration to a fraction of a pixel: what two frames of the same surfaces differ by); with no
    agreeing pair there is no floor to grant. A pair disagrees when its ratio holds at least the
    frame's texture plus that floor."""
    log_tex = _log_texture(linear)
    n = capture.num_frames
    pairs = {i: pair_residuals(capture, i, i + 1, usable, log_tex) for i in range(n - 1)}
    judged = {i: r for i, r in pairs.items() if r is not None}
    agreeing = [ratio for ratio, texture in judged.values() if ratio < texture]
    floor = min(agreeing, default=0.0)
    disagree = [[i, i + 1] for i, (ratio, texture) in judged.items() if ratio >= texture + floor]
    broken = {i for i, _ in disagree}
    longest = run = 1
    for i in range(n - 1):  # an unjudged pair does not split the clip
        run = 1 if i in broken else run + 1
        longest = max(longest, run)
    return {"pairs_checked": len(judged), "pairs_disagreeing": disagree, "noise_floor": round(floor, 4),
            "largest_agreeing_share": round(longest / max(n, 1), 4)}
