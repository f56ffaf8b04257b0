"""The main light on a field ESTIMATED from a panorama-room capture (real photographic HDR texture
on a box room, clipped to 8 bits by the capture: core.sim.panorama_room), at probes across the
room, against the source that dominates the irradiance there (the ground-truth map's own fit, which
is exact on ground truth: tests/test_lights.py). The simulated-capture counterpart is
tests/test_readme_examples.py. Prints the per-probe figures docs/integrations.md quotes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from capture_fixtures import PANORAMA, panorama_clip, walk_poses, write_nerfstudio
from light_truth import angle_deg

pytestmark = pytest.mark.slow
PROBES = [(0.0, 0.0, 0.0), (-0.6, 0.0, 0.0), (0.6, 0.1, -0.5), (0.0, 0.3, -0.3), (0.3, -0.2, 0.2),
          (-1.25, -0.75, -3.0), (-1.25, -0.75, -1.0), (-1.25, 0.75, -3.0), (-1.25, 0.75, -1.0),
          (1.25, -0.75, -3.0), (1.25, -0.75, -1.0), (1.25, 0.75, -3.0), (1.25, 0.75, -1.0)]


@pytest.fixture(scope="module")
def panorama_field(tmp_path_factory):
    from cli.main import main

    root = tmp_path_factory.mktemp("pano")
    poses = walk_poses(6)
    ldr, depth, intr = panorama_clip(poses, 160, 120, pano_height=256)
    write_nerfstudio(root / "cap", ldr, depth, intr, [np.asarray(p) for p in poses])
    assert main(["estimate", str(root / "cap"), "-o", str(root / "field"), "--preset", "draft", "--quiet"]) == 0
    return root / "field"


def test_main_light_on_a_field_estimated_from_a_panorama_capture(panorama_field):
    from core.fields.stored.artefact import LightFieldArtefact
    from core.lights import extract_dominant_light
    from core.sim.panorama_room import PanoramaRoom, load_panorama
    from core.tracking.room import assumed_room

    room = PanoramaRoom(load_panorama(PANORAMA, 256), assumed_room(), torch.zeros(3))
    art = LightFieldArtefact.load(panorama_field)
    rows = []
    for x in PROBES:
        truth = extract_dominant_light(room.envmap(x, 128).double())
        assert truth.found, truth.reason
        light = extract_dominant_light(art.envmap(x, None, 128)[0].double())
        off = angle_deg(light.direction, truth.direction)
        rows.append((off, light.found, light.confidence))
        print(f"\npanorama field, main light at {x}: {off:.0f} deg from the dominant source, "
              f"confidence {light.confidence:.2f}, found {light.found}")
    found_off = [off for off, found, _ in rows if found]
    broken = [off for off, found, _ in rows if found and off > 20.0]
    print(
        f"found {len(found_off)} of {len(rows)}; found but > 20 deg off: {len(broken)} "
        f"({', '.join(f'{o:.0f}' for o in broken)})"
    )
    # What holds today (docs/integrations.md): most found lights are within 20 deg, the median is;
    # NOT the full contract: the estimated field's own lamp blob is 17-47 deg off at some probes and
    # the fit, which reads the map, follows it with confidence 0.11-0.21.
    assert np.median(found_off) <= 20.0
    assert len(broken) <= 4, broken
