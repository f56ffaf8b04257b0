"""Every error the API returns is `{"error": {"code", "message"}}` with a specific status.

User-triggerable failures raise an `ApiError` subclass; the handlers installed by
`install_error_handlers` turn those, FastAPI's own validation errors and unexpected
exceptions into that body. Unexpected exceptions are logged with a traceback and answered
with a generic message, so internals (paths, stack frames) never reach a client. Losing
Redis (broker and job store) is not unexpected: it is a 503 `broker_unavailable` with
`Retry-After`, like every other 429/503 the API sends.
"""
from __future__ import annotations

import errno as errno_names
import logging
from contextlib import contextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from jobs.errors import broker_errors
from service.exports import ExportCancelled
from service.query_rules import FIELD_RULES

log = logging.getLogger("lightfield.service")


class ErrorDetail(BaseModel):
    code: str
    message: str


class ErrorBody(BaseModel):
    error: ErrorDetail


RETRY_AFTER_BROKER_S = 5  # Redis restarts in about a second (embedded) or fails over
RETRY_AFTER_JOBS_S = 30  # a draft job takes about a minute


class ApiError(Exception):
    status = 400
    default_code = "bad_request"

    def __init__(self, message: str, code: str | None = None, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.message = message
        self.code = code or self.default_code
        self.headers = headers


class BadRequest(ApiError):
    status, default_code = 400, "bad_request"


class Unauthorized(ApiError):
    status, default_code = 401, "unauthorized"

    def __init__(self, message: str = "missing or invalid API key (Authorization: Bearer KEY)"):
        super().__init__(message, headers={"WWW-Authenticate": "Bearer"})


class NotFound(ApiError):
    status, default_code = 404, "not_found"


class RequestTimeout(ApiError):
    status, default_code = 408, "request_timeout"

    def __init__(self, message: str, code: str | None = None):
        super().__init__(message, code, headers={"Connection": "close"})


class Conflict(ApiError):
    status, default_code = 409, "conflict"


class Gone(ApiError):
    """A stored file of the job failed verification: it is never served, and never retried."""

    status, default_code = 410, "artefact_corrupt"


class PayloadTooLarge(ApiError):
    status, default_code = 413, "too_large"


class UnsupportedMedia(ApiError):
    status, default_code = 415, "unsupported_media"


class InvalidInput(ApiError):
    status, default_code = 422, "invalid_input"


class Forbidden(ApiError):
    status, default_code = 403, "forbidden"


class TooManyJobs(ApiError):
    status, default_code = 429, "too_many_jobs"

    def __init__(self, message: str, retry_after_s: int = RETRY_AFTER_JOBS_S):
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


class ServiceUnavailable(ApiError):
    status, default_code = 503, "unavailable"

    def __init__(self, message: str, code: str | None = None, retry_after_s: int = RETRY_AFTER_BROKER_S):
        super().__init__(message, code, headers={"Retry-After": str(retry_after_s)})


BROKER_DOWN = "the job store and queue (Redis) are unreachable; try again shortly"
RETRY_AFTER_STORAGE_S = 30  # an operator frees or remounts a disk in minutes, not seconds


def storage_unavailable(exc: OSError, what: str) -> ServiceUnavailable:
    """503 storage_unavailable for an OSError of the storage root: the error's kind, never its path."""
    kind = errno_names.errorcode.get(exc.errno or 0, type(exc).__name__)
    reason = {"ENOSPC": "storage is full", "EDQUOT": "storage quota exceeded", "EROFS": "storage is read-only",
              "EACCES": "storage is not writable", "EPERM": "storage is not writable"}.get(kind, "storage error")
    log.warning("storage unavailable while %s: %s", what, exc)
    return ServiceUnavailable(f"{reason} ({kind}) while {what}; nothing was kept, try again later",
                              code="storage_unavailable", retry_after_s=RETRY_AFTER_STORAGE_S)


@contextmanager
def storage_errors(what: str):
    """Turn an OSError of the storage root (unwritable, full, gone) into 503 storage_unavailable."""
    try:
        yield
    except OSError as exc:
        raise storage_unavailable(exc, what) from None


def error_response(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    body = ErrorBody(error=ErrorDetail(code=code, message=message))
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


def describe_validation_errors(errors) -> str:
    """pydantic/FastAPI error list -> "field.path: message; ..." (names the offending fields).
    Query values with a rule of their own (service.query_rules.FIELD_RULES) are described by it and
    the value sent ("x: must be three finite numbers ..., got 'nan,0,0'"), not by the regular
    expression or the one bound that happened to fail."""
    parts = []
    for err in errors:
        loc = [str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path", "header")]
        where = ".".join(loc) or "request"
        rule = FIELD_RULES.get(loc[-1]) if loc and not loc[-1].isdigit() else None
        if rule is None and len(loc) >= 2 and loc[-1].isdigit():  # an element: queries.0.x.2 -> x[]
            rule = FIELD_RULES.get(loc[-2] + "[]")
        if rule is not None and isinstance(err.get("input"), (str, int, float)) and err.get("type") != "missing":
            parts.append(f"{where}: must be {rule}, got {str(err['input'])[:80]!r}")
        else:
            parts.append(f"{where}: {err.get('msg', 'invalid')}")
    return "; ".join(parts)


def malformed_json(errors) -> str | None:
    """The message for a body that is not JSON at all (pydantic's json_invalid), else None."""
    for err in errors:
        if err.get("type") == "json_invalid":
            at = next((p for p in err.get("loc", ()) if isinstance(p, int)), None)
            reason = (err.get("ctx") or {}).get("error", "JSON decode error")
            return f"request body is not valid JSON: {reason}" + (f" at character {at}" if at is not None else "")
    return None


PARSE_FAILURE = "There was an error parsing the body"  # FastAPI's detail when its json.loads raised


def body_parse_message(exc: BaseException) -> str:
    cause = exc.__cause__
    if isinstance(cause, RecursionError):
        return "request body: JSON nested too deeply to parse (arrays/objects inside each other; a batch is "\
               '{"queries": [{"x": [X, Y, Z], "t": T}, ...]})'
    return f"request body could not be parsed ({type(cause).__name__ if cause else 'unreadable'})"


_HTTP_CODES = {404: "not_found", 405: "method_not_allowed", 401: "unauthorized", 413: "too_large",
               408: "body_timeout"}
# query/body fields whose invalid values have their own code (docs/api.md, "Errors")
_FIELD_CODES = {
    "x": "invalid_x",
    "t": "invalid_t",
    "ev": "invalid_ev",
    "offset": "invalid_offset",
    "limit": "invalid_limit",
    "height": "invalid_height",
    "size": "invalid_size",
    "queries": "invalid_query",
}


def validation_code(errors) -> str:
    """The code of a request validation failure: the first offending field's own code when
    it has one (so `t=inf` is `invalid_t` whichever layer refused it), else invalid_request."""
    for err in errors:
        names = [p for p in err.get("loc", ()) if isinstance(p, str) and p not in ("body", "query", "path", "header")]
        for name in reversed(names):  # the most specific first: queries.3.x -> invalid_x
            if name in _FIELD_CODES:
                return _FIELD_CODES[name]
    return "invalid_request"


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_request: Request, exc: ApiError):
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError):
        malformed = malformed_json(exc.errors())
        if malformed is not None:
            return error_response(400, "malformed_body", malformed)
        return error_response(422, validation_code(exc.errors()), describe_validation_errors(exc.errors()))

    async def _broker_down(request: Request, exc: Exception):
        log.warning("%s %s: Redis unreachable (%s)", request.method, request.url.path, type(exc).__name__)
        return error_response(503, "broker_unavailable", BROKER_DOWN, {"Retry-After": str(RETRY_AFTER_BROKER_S)})

    for cls in broker_errors():
        app.add_exception_handler(cls, _broker_down)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_request: Request, exc: StarletteHTTPException):
        if exc.status_code == 400 and exc.detail == PARSE_FAILURE:
            return error_response(400, "malformed_body", body_parse_message(exc))
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        return error_response(exc.status_code, code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(ExportCancelled)
    async def _client_gone(request: Request, _exc: ExportCancelled):
        log.info("%s %s: the client left; its export was cancelled", request.method, request.url.path)
        return error_response(499, "client_closed", "the client closed the connection before the answer was ready")

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal_error", "internal server error (logged on the server)")
