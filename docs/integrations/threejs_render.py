"""Render docs/integrations/threejs-probe.png: the docs' three.js recipe run as is in headless
Chromium (WebGL through SwiftShader) on an env map and SH of a stored light field.

    python docs/integrations/threejs_render.py FIELD_DIR --x 1.6,1.0,2.0 [-o PNG]

Needs tests/node/node_modules (npm ci in tests/node) and /usr/bin/chromium. Left to right: a
chrome ball, a rough metal ball and a diffuse ball lit by PMREMGenerator(our EXR), then a
diffuse ball lit only by a LightProbe with `/sh?layout=threejs` + the main light.
"""
from __future__ import annotations

import argparse
import functools
import http.server
import json
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("field")
    p.add_argument("--x", required=True)
    p.add_argument("--height", type=int, default=256)
    p.add_argument("--exposure", type=float, default=1.0)
    p.add_argument("-o", "--output", default=str(Path(__file__).with_name("threejs-probe.png")))
    args = p.parse_args()
    from cli.main import main as cli

    with tempfile.TemporaryDirectory(dir=REPO / "docs" / "integrations") as tmp:
        out = Path(tmp)
        assert cli(["envmap", args.field, "--x", args.x, "--height", str(args.height), "-o", str(out / "env.exr")]) == 0
        import io
        from contextlib import redirect_stdout

        buf = io.StringIO()
        with redirect_stdout(buf):
            assert cli(["sh", args.field, "--x", args.x, "--layout", "threejs"]) == 0
        (out / "sh.json").write_text(buf.getvalue())
        handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(REPO))
        handler.log_message = lambda *a: None
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        rel = out.relative_to(REPO).as_posix()
        url = (f"http://127.0.0.1:{server.server_port}/docs/integrations/threejs_render.html"
               f"?dir=/{rel}&exposure={args.exposure}")
        try:
            subprocess.run(["chromium", "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                            "--enable-unsafe-swiftshader", "--hide-scrollbars", "--window-size=960,420",
                            "--virtual-time-budget=20000", f"--screenshot={Path(args.output).resolve()}", url],
                           check=True, timeout=120, capture_output=True)
        finally:
            server.shutdown()
    print(json.dumps({"output": args.output, "x": args.x}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
