"""core.tracking.config: the tracker's knobs are a typed section of the engine config, so an
ablation is `--set tracking.X=...`, not a commit."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from core.engine.presets import preset
from core.tracking.config import DEFAULT_TRACKING, TrackingConfig, tracking_config, using_tracking


def test_engine_config_carries_the_tracking_section_and_validates_overrides():
    draft = preset("draft")
    assert draft.tracking == DEFAULT_TRACKING
    tuned = draft.with_overrides({"tracking.direct.search_step_deg": 4.0, "tracking.rotation.min_inliers": 12})
    assert tuned.tracking.direct.search_step_deg == 4.0 and tuned.tracking.rotation.min_inliers == 12
    assert tuned.model_dump()["tracking"]["direct"]["search_step_deg"] == 4.0  # recorded with the artefact
    with pytest.raises(ValidationError, match="search_step_deg"):
        draft.with_overrides({"tracking.direct.search_step_deg": -1})
    with pytest.raises(ValidationError, match="no_such_knob"):
        draft.with_overrides({"tracking.direct.no_such_knob": 1})


def test_the_tracker_reads_the_active_settings_and_they_do_not_leak():
    from core.tracking.direct import _search_grid

    start = np.eye(3)
    default = len(_search_grid(start))
    with using_tracking(TrackingConfig.model_validate({"direct": {"search_step_deg": 10.0}})) as cfg:
        assert tracking_config() is cfg
        coarser = len(_search_grid(start))
    assert coarser < default and len(_search_grid(start)) == default
    assert tracking_config() is DEFAULT_TRACKING
    with using_tracking(None):
        assert tracking_config() is DEFAULT_TRACKING


def test_the_knobs_left_their_modules():
    import core.tracking.direct as direct
    import core.tracking.rotation as rotation
    import core.tracking.track as track

    for module, name in ((direct, "SEARCH_STEP_DEG"), (rotation, "MIN_INLIERS"), (track, "FALLBACK_RATIO")):
        assert not hasattr(module, name), f"{module.__name__}.{name} is a knob: core.tracking.config holds it"
