"""The tracker's tuning knobs, one typed section per stage (TrackingConfig), so an ablation is a
setting and not a commit: `EngineConfig.tracking`, `--set tracking.direct.search_step_deg=4`
in the benches that take `--set`.

The tracker reads the active settings (`tracking_config()`) when it runs; `using_tracking(cfg)`
makes `cfg` the active settings for the code inside it (core.capture.prepare wraps tracking in
it when given `tracking=`, as run_job gives its config's section), and outside any
`using_tracking` the defaults here hold. A context variable rather than an argument down every
call: the knobs sit five calls deep in the tracker, and a value set for one job must not leak
into another thread's job. Imports nothing of core, so any layer may read it.

What stays a module constant in core/tracking: the assumed room's size (core.tracking.room: the
capture's depth and the room share it), the grid search's dtype, COLMAP's thread count (one, so
every run gives the same poses) and the texts of warnings."""
from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

from core.active_settings import ActiveSettings


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FeaturesConfig(_Section):
    """SIFT features and their matching (core.tracking.features)."""

    analysis_max_side: int = Field(480, ge=32, description="frames are tracked with their long side at most this")
    max_features: int = Field(1500, ge=10)
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe's ratio test, both ways")
    # lowered for low-texture frames (a plain wall, a dim room) until min_features are found:
    # weak features are only kept when strong ones are missing, and matching drops their noise
    contrast_thresholds: tuple[float, ...] = Field((0.02, 0.01, 0.005), min_length=1)
    min_features: int = Field(150, ge=1)


class MotionConfig(_Section):
    """Does the camera move? (core.tracking.motion)"""

    min_matches: int = Field(12, ge=1, description="mutual matches that make a frame pair usable")
    # 0.4 % of the width: ~1.3 px at 320 px, ~0.25 deg at 60 deg FOV
    min_motion_fraction: float = Field(0.004, ge=0)
    k_sigma: float = Field(4.0, ge=0, description="threshold in units of the keypoint noise")
    still_px: float = Field(0.5, ge=0, description="a feature that moved less (analysis pixels) stayed put")
    still_min: int = Field(6, ge=1, description="that many matches staying put mean a still camera")


class RotationConfig(_Section):
    """Pans from one spot: pairwise rotations, their consensus and the bundle adjustment
    (core.tracking.rotation)."""

    inlier_px: float = Field(2.0, gt=0)
    # an outlier lands within inlier_px of where a 3-parameter rotation puts it with a chance of
    # about 2e-4 at 320 px, so ten agreeing by chance does not happen; dim, noisy pans match
    # 10-60 features a pair, and at 15 their pairs fell apart
    min_inliers: int = Field(10, ge=3)
    essential_min_inliers: int = Field(15, ge=5, description="five parameters fitted to a rotation's noise")
    ransac_iterations: int = Field(200, ge=1)
    # a pair's candidate rotations: the room's and, where something moves through the view, its
    pair_hypotheses: int = Field(2, ge=1)
    # candidates this close are one vote (1 deg is 2.7 px at 160 px and 60 deg, above inlier_px,
    # while a passer-by crossing a pan moves several degrees a frame against the room)
    consensus_deg: float = Field(1.0, gt=0)
    agree_deg: float = Field(3.0, gt=0, description="a pair's candidate is used within this of the placed rotations")
    ba_rounds: int = Field(2, ge=1)
    max_pair_observations: int = Field(150, ge=1)
    # the rotation model explains the motion when fit_inlier_share of the matches are its inliers
    # and its median residual is within fit_ratio of an essential matrix's (parallax raises only
    # the latter), or below fit_floor_px: pans measure 1.1-1.3x, a 1.3 m walk 4.8-10x
    fit_ratio: float = Field(2.0, gt=0)
    fit_floor_px: float = Field(0.3, ge=0)
    fit_inlier_share: float = Field(0.6, ge=0, le=1)
    max_readout: float = Field(1.0, gt=0, description="|readout| in frame intervals: never longer than a frame")
    # the rolling shutter is fitted where the global-shutter rotations leave at most this many
    # times the essential matrix's residual: blur and noise raise a pan to about 3, a walk's
    # parallax to 4.8-10, where the readout only runs to its bound
    rolling_max_ratio: float = Field(4.0, gt=0)


class DirectConfig(_Section):
    """Photometric tracking of room scans (core.tracking.direct)."""

    pyramid_heights: tuple[int, ...] = Field((18, 36, 72), min_length=1, description="rows per level, coarse to fine")
    search_step_deg: float = Field(5.0, gt=0, description="the coarse grid's spacing around a starting guess")
    search_span_deg: float = Field(30.0, gt=0, description="... and its half-width in yaw and pitch")
    roll_span_deg: float = Field(30.0, ge=0, description="a ring looking 40 deg down turns 0.64 of its yaw as roll")
    local_span_deg: float = Field(4.0, gt=0, description="the finer grid around each coarse survivor")
    local_step_deg: float = Field(2.0, gt=0)
    local_candidates: int = Field(6, ge=1, description="... of which the best are refined there")
    coarse_candidates: int = Field(24, ge=1, description="distinct best grid rotations refined on the coarse level")
    survivors: tuple[int, ...] = Field((24, 3, 2), min_length=1, description="candidates kept after each level")
    grid_iterations: int = Field(2, ge=0, description="Gauss-Newton steps a grid rotation takes before comparison")
    gn_iterations: tuple[int, ...] = Field((6, 4, 3), min_length=1, description="Gauss-Newton steps per level")
    max_step_deg: float = Field(3.0, gt=0, description="a Gauss-Newton step turns by at most this")
    robust_scale: float = Field(0.05, gt=0, description="LDR units: pseudo-Huber scale of the residual")
    # candidates are compared by the textured pixels they explain: residual within score_cap times
    # what 8-bit and compression noise (score_noise) and a misregistration of score_subpixel leave
    score_cap: float = Field(3.0, gt=0)
    score_noise: float = Field(0.01, gt=0)
    score_subpixel: float = Field(0.5, ge=0)
    min_depth: float = Field(0.1, description="a bearing at this cosine to frame j's axis or less is out of its view")
    min_overlap: float = Field(0.15, gt=0, le=1, description="share of frame i's usable pixels frame j must show")
    max_pair_cost: float = Field(0.0004, gt=0, description="mean robust cost above which a pair is not trusted")
    max_pair_sigma_deg: float = Field(1.0, gt=0, description="a pair fixes the rotation within this")
    info_step_deg: float = Field(1.5, gt=0, description="the differences the information is measured over")
    min_residual_sigma: float = Field(0.004, gt=0, description="floor of a pair's residual noise (8-bit, codec)")
    motion_sigma_deg: float = Field(5.0, gt=0, description="prior: a turn differs from the last by about this")
    dark_ldr: float = Field(0.03, ge=0, description="usable pixels: not sunk into the black ...")
    bright_ldr: float = Field(0.97, le=1, description="... nor clipped")
    loop_max_axis_deg: float = Field(40.0, gt=0, description="frames with axes this close are tried as loop closures")
    loop_min_gap: int = Field(3, ge=1, description="... when this many frames apart (neighbours are paired already)")
    loop_span_deg: float = Field(10.0, gt=0, description="a loop closure searches this far around the chain's guess")
    near_span_deg: float = Field(10.0, gt=0, description="a consecutive pair first searches this far")
    near_candidates: int = Field(4, ge=1, description="... and refines this many of that grid's best")
    near_roll_span_deg: float = Field(5.0, ge=0, description="... and this far in roll")
    # a near answer costing more than this x the clip's median pair cost is checked on the full grid
    near_cost_ratio: float = Field(3.0, gt=0)
    max_loop_pairs: int = Field(120, ge=0)
    # a consecutive pair overlapping less than weak_overlap_ratio x min_overlap, at near_cost_ratio
    # x the usual cost, is not trusted
    weak_overlap_ratio: float = Field(2.0, gt=0)
    # the focal-length fit's range: a 60 deg guess for a 49-73 deg lens
    max_log_focal_scale: float = Field(math.log(1.25), ge=0)
    # chi-square of one parameter at p = 0.001: what the focal fit must explain to be kept
    focal_fit_chi2: float = Field(10.83, ge=0)

    @property
    def weak_overlap(self) -> float:
        return self.weak_overlap_ratio * self.min_overlap


class SfmConfig(_Section):
    """Structure from motion (core.tracking.sfm, pycolmap)."""

    # the mapper's starts (initial-pair angles), the first preferred: 4 deg lets a phone's small
    # baselines start a model
    init_min_tri_angles_deg: tuple[float, ...] = Field((4.0, 8.0, 16.0), min_length=1)
    # another start's model replaces the first's only with a pooled median error this many times
    # the first's or lower: smaller differences went either way on walks
    clearly_better: float = Field(0.9, gt=0)
    exhaustive_max_frames: int = Field(40, ge=2, description="more frames are matched sequentially")
    sequential_overlap: int = Field(10, ge=1)
    max_features: int = Field(2048, ge=10)


class TwoViewConfig(_Section):
    """OpenCV's incremental two-view fallback (core.tracking.twoview)."""

    init_candidates: int = Field(8, ge=1, description="frames after frame 0 tried as its initial partner")
    init_max_h_ratio: float = Field(0.9, gt=0, description="a partner a homography explains this well is too close")
    max_reproj_px: float = Field(2.0, gt=0)
    min_parallax_deg: float = Field(1.0, ge=0)
    min_pnp: int = Field(12, ge=4)
    neighbours: int = Field(4, ge=1)


class TrackConfig(_Section):
    """Choosing between the trackers (core.tracking.track)."""

    min_kept_fraction: float = Field(0.5, ge=0, le=1, description="a track registering fewer frames fails")
    # the rotation track stands in when structure from motion fails: it must explain this share of
    # the matches with a median residual within this many pixels, and may exceed an essential
    # matrix's residual by up to fallback_ratio (handheld pans with blur and noise: inliers
    # 0.95-1.00, medians 0.49-0.82 px, ratios 2.06-2.76; walks with parallax 4.8-10)
    fallback_inlier_share: float = Field(0.9, ge=0, le=1)
    fallback_max_median_px: float = Field(1.0, gt=0)
    fallback_ratio: float = Field(3.0, gt=0)
    # ... or, where nothing else registered the clip, a median residual within this many times the
    # keypoint noise: pure noise leaves about 0.7x
    fallback_noise_ratio: float = Field(2.0, gt=0)
    # the photometric track must agree with the features' rotations this well: theirs err by 2-2.5
    # deg on a scan's tilts and turn a few degrees more at a refitted focal length over a ring; a
    # track that went wrong is tens of degrees off
    direct_max_disagreement_deg: float = Field(10.0, gt=0)
    # of the pairs tried (consecutive and loop closures) that must agree: room scans 81-100 %; a
    # still camera forced into a turn by someone walking through, 57 %
    direct_min_matched_share: float = Field(0.7, ge=0, le=1)


class GeometryConfig(_Section):
    """What tracking adds to a capture: focal length and room (core.tracking.capture_geometry)."""

    min_self_calibration_span_deg: float = Field(15.0, ge=0, description="a pan this wide refines the focal length")
    self_calibration_hfov_range: tuple[float, float] = (20.0, 130.0)
    min_room_points: int = Field(30, ge=1, description="triangulated points that place the room's walls")
    min_depth_samples: int = Field(20, ge=1, description="depth pixels that fix the track's scale")


class TrackingConfig(_Section):
    features: FeaturesConfig = FeaturesConfig()
    motion: MotionConfig = MotionConfig()
    rotation: RotationConfig = RotationConfig()
    direct: DirectConfig = DirectConfig()
    sfm: SfmConfig = SfmConfig()
    twoview: TwoViewConfig = TwoViewConfig()
    track: TrackConfig = TrackConfig()
    geometry: GeometryConfig = GeometryConfig()


DEFAULT_TRACKING = TrackingConfig()
_ACTIVE = ActiveSettings("tracking_config", DEFAULT_TRACKING)


def tracking_config() -> TrackingConfig:
    """The settings the tracker runs with now."""
    return _ACTIVE.get()


def using_tracking(config: TrackingConfig | None):
    """Track with `config` inside the block (None: the settings already active)."""
    return _ACTIVE.using(config)
