"""What each query value of the HTTP API must be: the bounds, the pattern of a position and the
rule in words. service.queries checks values against them and service.errors describes a
refused value by its rule (not by the regular expression or the one bound that failed); both
import them from here, which imports nothing of the service."""
from __future__ import annotations

MAX_ABS_EV = 64.0
MAX_ABS_X_M = 1e6  # positions: metres from the capture's origin (indoor scenes span metres)
MAX_ABS_T_S = 1e9  # times: seconds from the first frame


def _bound(v: float) -> str:
    return f"{v:.0e}".replace("e+0", "e").replace("e+", "e") if v >= 1e5 else f"{v:g}"


FIELD_RULES = {
    "x": f"three finite numbers 'X,Y,Z' in metres, each within +-{_bound(MAX_ABS_X_M)}",
    "x[]": f"a finite number of metres within +-{_bound(MAX_ABS_X_M)}",  # one coordinate of a JSON x
    "t": f"a finite number of seconds within +-{_bound(MAX_ABS_T_S)}",
    "t0": f"a finite number of seconds within +-{_bound(MAX_ABS_T_S)}",
    "t1": f"a finite number of seconds within +-{_bound(MAX_ABS_T_S)}",
    "ev": f"a finite number of stops within +-{_bound(MAX_ABS_EV)}",
    "height": "a whole number of rows >= 1",
    "size": "a whole number of texels >= 1",
    "frames": "a whole number of frames >= 1",
    "offset": "a whole number >= 0",
    "limit": "a whole number >= 1",
}
_NUMBER = r"\s*[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?\s*"
X_PATTERN = rf"^{_NUMBER},{_NUMBER},{_NUMBER}$"
