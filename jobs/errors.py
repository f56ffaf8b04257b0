"""Error codes of a job's input errors: the same whether the API's upload check or the
worker meets the error, as docs/api.md lists them."""
from __future__ import annotations


def user_error_types() -> tuple[type[BaseException], ...]:
    """Errors caused by the job's input: recorded with their code, never retried."""
    from core.camera import CameraError  # noqa: PLC0415 — core.camera pulls in torch: imported when used
    from core.capture.base import CaptureError  # noqa: PLC0415 — core.capture.base pulls in torch: imported when used
    from core.io.limits import MediaError  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL, torch: imported when used
    from core.priors.base import PriorError  # noqa: PLC0415 — core.priors.base pulls in pydantic, torch: imported when used

    return (MediaError, CaptureError, CameraError, PriorError)


def error_code_of(exc: BaseException) -> str:
    """The API error code of an input error (a `.code`, else one derived from the input it names)."""
    code = getattr(exc, "code", None)
    if isinstance(code, str) and code:
        return code
    field = getattr(exc, "field", None)  # CaptureError names its input, as the API's codes do
    if isinstance(field, str) and field.isidentifier():
        return f"invalid_{field}"
    return {"CaptureError": "invalid_capture", "CameraError": "invalid_intrinsics",
            "PriorError": "prior_unavailable"}.get(type(exc).__name__, "invalid_input")


def broker_errors() -> tuple[type[BaseException], ...]:
    """Redis (broker and job store) unreachable: an outage to wait out, never the job's fault."""
    import redis  # noqa: PLC0415 — redis is heavy: imported when used
    from kombu.exceptions import OperationalError  # noqa: PLC0415 — kombu is heavy: imported when used

    return (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError, OperationalError)
