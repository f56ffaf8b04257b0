"""Do neighbouring frames agree where the capture says they overlap?

The field is fitted to the frames as the capture reads them, so re-rendering the frames from it
(core.engine.self_check) cannot see a misread the field could absorb: a field with a time input
explains frames from two rooms as a change of light, and one without explains a track that drifts
by blurring what it saw. Geometry can see it. Each frame's pixels are carried through its depth
and pose into the next frame; if the capture is read right, the next frame saw the same surfaces,
so it predicts their texture up to a gain (an exposure step or a change of light scales what a
surface sends, it does not move or repaint it: the pair's median log ratio is removed first).

The reference, as for the field, is the constant map: a frame's own texture about its median.
A neighbour that predicts the texture no better than a flat colour does has not seen the same
surfaces where the poses and depth put them: a track that turned the wrong way, depth at the wrong
scale, a cut to another scene. No threshold is learned; a pair with too little overlap to say is
not counted. What it cannot tell: a wrong exposure course (a gain, like a light dimming evenly)
and errors small enough that the neighbour still predicts better than a flat colour.
"""
from __future__ import annotations

import torch

from core.capture.base import Capture
from core.conventions import valid_depth_mask

MIN_OVERLAP = 16  # pixels of a pair that must land in the neighbour before it is judged
_EPS = 1e-6


def _log_texture(linear: torch.Tensor) -> torch.Tensor:
    return torch.log(linear.clamp_min(_EPS)).mean(-1)


def pair_residuals(capture: Capture, i: int, j: int, usable: torch.Tensor, log_tex: torch.Tensor
                   ) -> tuple[float, float] | None:
    """(neighbour's residual, constant's residual) of frame i's usable pixels predicted by frame j
    through depth and poses, each the median |log| error after the pair's gain; None: too little overlap."""
    depth = capture.depth[i]
    keep = usable[i] & valid_depth_mask(depth)
    if int(keep.sum()) < MIN_OVERLAP:
        return None
    points = capture.camera(i).unproject(depth.double())[keep]
    u, v, z = capture.camera(j).project(points)
    col, row = u.floor().long(), v.floor().long()
    inside = (z > 0) & (col >= 0) & (col < capture.width) & (row >= 0) & (row < capture.height)
    col, row = col.clamp(0, capture.width - 1), row.clamp(0, capture.height - 1)
    inside &= usable[j][row, col]
    if int(inside.sum()) < MIN_OVERLAP:
        return None
    mine = log_tex[i][keep][inside]
    theirs = log_tex[j][row[inside], col[inside]]
    diff = mine - theirs
    neighbour = float((diff - diff.median()).abs().median())
    constant = float((mine - mine.median()).abs().median())
    return neighbour, constant


def frame_agreement(capture: Capture, usable: torch.Tensor, linear: torch.Tensor) -> dict:
    """Consecutive frames compared through depth and poses (module docstring): the pairs checked,
    those whose neighbour predicts worse than a flat colour, and the longest run of frames joined by
    agreeing pairs (a share of the frames)."""
    log_tex = _log_texture(linear)
    n = capture.num_frames
    checked, disagree = 0, []
    joined = [True] * max(n - 1, 0)  # an unjudged pair does not split the clip
    for i in range(n - 1):
        res = pair_residuals(capture, i, i + 1, usable, log_tex)
        if res is None:
            continue
        checked += 1
        if res[0] >= res[1]:
            disagree.append([i, i + 1])
            joined[i] = False
    longest = run = 1
    for ok in joined:
        run = run + 1 if ok else 1
        longest = max(longest, run)
    return {"pairs_checked": checked, "pairs_disagreeing": disagree,
            "largest_agreeing_share": round(longest / max(n, 1), 4)}
