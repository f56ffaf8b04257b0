"""docs/integrations.md's three.js recipes run as they are in headless Chromium (WebGL 2 through
SwiftShader) against a local server that answers their URLs with our products, then three.js
itself samples what they built: `scene.background` (the texture exactly as three's shaders read
it) and the PMREM environment, along random directions, compared with our radiance there.

Chromium: `chromium` on PATH (.ci/run installs it) or LIGHTFIELD_CHROMIUM; three: tests/node
(npm ci). Skipped, with the reason, without Chromium."""
from __future__ import annotations

import html
import http.server
import json
import os
import re
import shutil
import subprocess
import threading
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
import torch

from core.conventions import equirect_directions
from core.envmap import sample_envmap

REPO = Path(__file__).resolve().parents[1]
THREE_DIR = REPO / "tests" / "node" / "node_modules" / "three"
CHROMIUM = os.environ.get("LIGHTFIELD_CHROMIUM") or shutil.which("chromium")
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(
        not CHROMIUM, reason="no chromium on PATH (apt-get install chromium; or set LIGHTFIELD_CHROMIUM)"
    ),
]

LAMPS = (((0.6, 0.3, -0.74), (30.0, 8.0, 2.0)), ((-0.5, -0.2, 0.84), (2.0, 6.0, 20.0)))  # warm at +x, blue at -x/+z


def room(height: int) -> torch.Tensor:
    """A smooth map two coloured lamps make asymmetric in every axis: a mirrored or rotated texture shows."""
    d = equirect_directions(height, dtype=torch.float64)
    env = torch.full((height, 2 * height, 3), 0.3, dtype=torch.float64)
    for direction, rgb in LAMPS:
        mu = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float64), dim=0)
        env = env + torch.exp(12.0 * (d @ mu - 1.0))[..., None] * torch.tensor(rgb, dtype=torch.float64)
    return env.float()


def js_blocks(section: str) -> list[str]:
    text = (REPO / "docs" / "integrations.md").read_text()
    start = text.index(f"\n## {section}")
    end = text.find("\n## ", start + 5)
    return re.findall(r"```js\n(.*?)```", text[start:end if end > 0 else None], re.S)


HARNESS = """<!doctype html><html><body><pre id="out">pending</pre>
<script type="importmap">{"imports": {"three": "/three/build/three.module.js",
                             "three/addons/": "/three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
const out = document.getElementById('out');
try {
  const renderer = new THREE.WebGLRenderer();
  renderer.setSize(4, 4);
  const scene = new THREE.Scene();
  Object.assign(globalThis, { renderer, scene, LF: '', job: 'job' });
  await import('/recipe.mjs');                       // the docs' block, verbatim
  const rt = new THREE.WebGLRenderTarget(1, 1, { type: THREE.FloatType });
  const camera = new THREE.PerspectiveCamera(0.5, 1, 0.01, 10);
  const sample = () => DIRS.map((d) => {
    camera.lookAt(...d); camera.updateMatrixWorld();
    renderer.setRenderTarget(rt); renderer.render(scene, camera);
    const px = new Float32Array(4); renderer.readRenderTargetPixels(rt, 0, 0, 1, 1, px);
    return [px[0], px[1], px[2]];
  });
  const background = sample();
  scene.background = scene.environment; scene.backgroundBlurriness = 0;  // the PMREM at roughness 0
  const pmrem = sample();
  const lights = scene.children.filter((c) => c.isLight).map((c) => ({ type: c.type,
    sh: c.sh ? c.sh.toArray() : null, position: c.position.toArray(), color: c.color.toArray() }));
  out.textContent = JSON.stringify({ background, pmrem, lights,
    backgroundType: scene.background && scene.background.constructor.name });
} catch (e) { out.textContent = JSON.stringify({ error: String((e && e.stack) || e) }); }
</script></body></html>"""


class _Handler(http.server.BaseHTTPRequestHandler):
    """Serves three from tests/node, the harness, the recipe, and the recipe's /lightfield URLs
    answered with our products (the same core.export functions the API's routes call)."""

    recipe = ""
    cube_layout = None  # force a layout (to show the wrong one fails)
    dirs: list = []

    def log_message(self, *args):
        pass

    def _send(self, body: bytes, kind: str):
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self):
        url = urllib.parse.urlparse(self.path)
        q = {k: v[0] for k, v in urllib.parse.parse_qs(url.query).items()}
        if url.path.startswith("/three/"):
            path = (THREE_DIR / url.path[len("/three/"):]).resolve()
            assert THREE_DIR.resolve() in path.parents
            return self._send(path.read_bytes(), "text/javascript")
        if url.path == "/page.html":
            return self._send(HARNESS.replace("DIRS", json.dumps(self.dirs)).encode(), "text/html")
        if url.path == "/recipe.mjs":
            return self._send(self.recipe.encode(), "text/javascript")
        if url.path == "/lightfield/job/envmap":
            from core.io.envmap_io import encode_envmap

            data, kind = encode_envmap(room(int(q["height"])).numpy(), q["format"])
            return self._send(data, kind)
        if url.path == "/lightfield/job/sh":
            from core.export.schema import Flags, SphericalHarmonics
            from core.lights import extract_dominant_light
            from core.sh import project_sh

            env = room(128)
            doc = SphericalHarmonics.of((1.6, 1.0, 2.0), 0.0, Flags(x=False, t=False), q.get("layout", "arcore"),
                                        extract_dominant_light(env), project_sh(env.double()))
            return self._send(doc.model_dump_json().encode(), "application/json")
        if url.path == "/lightfield/job/cubemap":
            from core.export.products import cube_ktx2, cube_source_height

            size = int(q["size"])
            data = cube_ktx2(
                room(cube_source_height(size)), size, int(q["levels"]), self.cube_layout or q.get("layout", "gl")
            )
            return self._send(data, "image/ktx2")
        self.send_error(404)


def run_recipe(recipe: str, dirs: np.ndarray, tmp_path, cube_layout=None) -> dict:
    handler = type("Handler", (_Handler,), {"recipe": recipe, "cube_layout": cube_layout, "dirs": dirs.tolist()})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        proc = subprocess.run([CHROMIUM, "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                               "--enable-unsafe-swiftshader", f"--user-data-dir={tmp_path / 'profile'}",
                               "--virtual-time-budget=60000", "--dump-dom",
                               f"http://127.0.0.1:{server.server_port}/page.html"],
                              capture_output=True, text=True, timeout=180)
    finally:
        server.shutdown()
    found = re.search(r'<pre id="out">(.*?)</pre>', proc.stdout, re.S)
    assert found, (proc.stdout[-2000:], proc.stderr[-2000:])
    out = json.loads(html.unescape(found.group(1)))
    assert "error" not in out, out["error"]
    return out


def _directions(n=24, seed=3) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(4 * n, 3, generator=g, dtype=torch.float64), dim=-1)
    return d[d[:, 1].abs() < 0.9][:n].numpy()  # away from the poles (camera.lookAt's up vector)


def _errors(got, dirs) -> tuple[float, float]:
    want = sample_envmap(room(256).double(), torch.from_numpy(dirs)).numpy()
    err = np.abs(np.asarray(got) - want).max(axis=-1) / want.max()
    return float(err.mean()), float(err.max())


@pytest.fixture(scope="module")
def three_installed(node_consumers):
    assert THREE_DIR.is_dir()
    return THREE_DIR


def test_threejs_exr_and_sh_recipe_gives_our_radiance_in_three(three_installed, tmp_path):
    exr_block, cube_block = js_blocks("three.js")
    dirs = _directions()
    out = run_recipe(exr_block, dirs, tmp_path)
    for name in ("background", "pmrem"):
        mean, worst = _errors(out[name], dirs)
        print(f"\nthree.js EXR recipe, {name}: error of the peak mean {mean:.2%}, worst {worst:.2%}")
        assert mean < 0.02 and worst < 0.08, (name, mean, worst)
    kinds = sorted(light["type"] for light in out["lights"])
    assert kinds == ["DirectionalLight", "LightProbe"], kinds  # the SH part ran with the API's field names


def test_threejs_ktx2_cube_recipe_builds_a_cube_three_samples_right(three_installed, tmp_path):
    exr_block, cube_block = js_blocks("three.js")
    dirs = _directions()
    out = run_recipe(cube_block, dirs, tmp_path)
    assert out["backgroundType"] in ("CubeTexture", "Texture")
    for name in ("background", "pmrem"):
        mean, worst = _errors(out[name], dirs)
        print(
            f"\nthree.js KTX2 cube recipe (layout=threejs), {name}: error of the peak mean {mean:.2%}, worst "
            f"{worst:.2%}"
        )
        assert mean < 0.02 and worst < 0.08, (name, mean, worst)
    # the GL-table cube three.js users were told to load before is mirrored in x there
    wrong = run_recipe(cube_block, dirs, tmp_path, cube_layout="gl")
    mean, worst = _errors(wrong["background"], dirs)
    print(f"three.js KTX2 cube recipe with layout=gl: error of the peak mean {mean:.2%}, worst {worst:.2%}")
    assert worst > 0.3
