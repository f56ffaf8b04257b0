"""core.capture.config: the capture stage's knobs (so far the transients stage's) are a typed
section of the engine config, read when the stage runs."""
from __future__ import annotations

import pytest
from pydantic import ValidationError

from core.capture.config import DEFAULT_CAPTURE, CaptureConfig, capture_config, using_capture
from core.engine.presets import preset


def test_engine_config_carries_the_capture_section_and_validates_overrides():
    draft = preset("draft")
    assert draft.capture == DEFAULT_CAPTURE
    tuned = draft.with_overrides({"capture.transients.min_frames": 12})
    assert tuned.capture.transients.min_frames == 12
    with pytest.raises(ValidationError, match="max_frame_share"):
        draft.with_overrides({"capture.transients.max_frame_share": 2.0})


def test_the_transients_stage_reads_the_active_settings():
    import core.capture.transients as transients

    assert transients._rank(12) == 3 and not hasattr(transients, "RANK")
    with using_capture(CaptureConfig.model_validate({"transients": {"rank": 4}})):
        assert transients._rank(12) == 4 and transients._rank(8) == 2
    assert capture_config() is DEFAULT_CAPTURE and transients._rank(12) == 3


def test_the_bench_helper_applies_both_sections():
    from bench.overrides import knobs_of
    from core.tracking.config import tracking_config

    config = preset("draft").with_overrides({"capture.transients.rank": 2, "tracking.rotation.min_inliers": 20})
    with knobs_of(config):
        assert capture_config().transients.rank == 2 and tracking_config().rotation.min_inliers == 20
    assert capture_config() is DEFAULT_CAPTURE and tracking_config().rotation.min_inliers == 10
    with knobs_of(None):
        assert capture_config() is DEFAULT_CAPTURE
