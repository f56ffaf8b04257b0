"""Physically based AR sessions (issue 61): rooms rendered with Mitsuba 3, captured as AR apps
send them, run through the product and scored against rendered ground truth.

* `bench.pbr.scenes`: the rooms, their lights' schedules, camera paths and probes, as plain
  JSON-able dicts (a scene's description is what its renders are cached by);
* `bench.pbr.render`: Mitsuba scene dicts built from a description, frames (RGB + planar depth)
  and ground-truth cube faces, every render cached by a hash of what it depends on;
* `bench.pbr.camera`: the phone camera (lagging auto-exposure, shot + read noise, the sRGB
  curve, 8-bit, H.264) and the four uploads of a session (full AR, monocular, LiDAR-like depth,
  no frame_ev);
* `bench.pbr.truth`: ground-truth env maps per light source at the probes (light is linear
  in the sources: any time's map is a sum of the sources' maps scaled by their schedules);
* `bench.pbr.score`: the scores (three spheres against the constant map, lamp direction, switch
  ratio, /sh main light, SH irradiance, drift).

Mitsuba is an optional dependency (the `dev` extra): it is imported lazily, inside functions.
The entry point is `python -m bench.pbr_sessions`.
"""
