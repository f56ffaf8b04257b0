"""`lightfield stream CAPTURE`: replay a capture as a live session and print each version of
the field as it lands (cli.session_replay; docs/api.md, "Live sessions")."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

HELP = "Replay a capture (video + params, nerfstudio zip, capture directory) as a live session at its frame rate."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", help="video, image sequence capture directory or nerfstudio zip/directory")
    p.add_argument("--depth", default=None, help="depth file for a video (.npz/.npy/EXR/16-bit PNG)")
    p.add_argument("--params", default=None, help="JSON object or file: the job params (intrinsics, fps, ...)")
    p.add_argument("--url", default=os.environ.get("LIGHTFIELD_URL", "http://127.0.0.1:8000"),
                   help="the service (env LIGHTFIELD_URL)")
    p.add_argument("--key-env", default="LIGHTFIELD_API_KEY",
                   help="environment variable holding the API key (keys never go on the command line)")
    p.add_argument("--probe", action="append", default=None, metavar="X,Y,Z",
                   help="probe point to follow (repeatable; default 0,0,-1: a metre in front of the first camera)")
    p.add_argument("--batch", type=int, default=1, help="frames per request")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed (x the capture's frame rate; 0: no pacing)")
    p.add_argument("--keep", action="store_true", help="leave the session open at the end (default: end it)")
    p.add_argument("--json", action="store_true", help="print each version event as one JSON line")


def run(args: argparse.Namespace) -> int:
    from cli.session_replay import SessionClient, read_capture, replay

    params = {}
    if args.params:
        text = args.params.strip()
        params = json.loads(Path(text).read_text() if not text.startswith("{") and Path(text).is_file() else text)
    capture = read_capture(Path(args.capture), Path(args.depth) if args.depth else None, params)
    client = SessionClient(args.url, os.environ.get(args.key_env))
    t0 = time.monotonic()

    def on_event(name: str, data: dict) -> None:
        if name == "version":
            if args.json:
                print(json.dumps(data), flush=True)
                return
            probe = data["probes"][0]
            light = probe["primaryLightDirection"]
            print(f"{time.monotonic() - t0:7.2f} s  version {data['version']:3d}  frames {data['frames']:4d}  "
                  f"SH[0] {probe['sphericalHarmonicsCoefficients'][0]:.4g}  main light "
                  f"({light['x']:+.2f}, {light['y']:+.2f}, {light['z']:+.2f})"
                  f"{'' if probe['primaryLightFound'] else ' (weak)'}", flush=True)
        elif name == "ended":
            print(f"{time.monotonic() - t0:7.2f} s  ended: stored field {data.get('lightfield')}", flush=True)
        elif name == "error":
            print(f"{time.monotonic() - t0:7.2f} s  error: {data}", file=sys.stderr, flush=True)

    try:
        sid = client.open(capture.params)
        print(f"session {sid}: {len(capture.frames)} frames at {capture.fps:g} fps", flush=True)
        follower = client.follow(sid, args.probe or ["0,0,-1"], on_event)
        replay(client, sid, capture, batch=max(1, args.batch), speed=args.speed)
        if args.keep:
            time.sleep(2.0)
            return 0
        client.end(sid)
        follower.join(timeout=600)
        return 0
    except RuntimeError as exc:
        print(f"stream: {exc}", file=sys.stderr)
        return 1
    finally:
        client.close()
