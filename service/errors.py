"""Every error the API returns is `{"error": {"code", "message"}}` with a specific status.

User-triggerable failures raise an `ApiError` subclass; the handlers installed by
`install_error_handlers` turn those, FastAPI's own validation errors and unexpected
exceptions into that body. Unexpected exceptions are logged with a traceback and answered
with a generic message, so internals (paths, stack frames) never reach a client.
"""
from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("lightfield.service")


class ErrorDetail(BaseModel):
    code: str
    message: str


class ErrorBody(BaseModel):
    error: ErrorDetail


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


class Conflict(ApiError):
    status, default_code = 409, "conflict"


class PayloadTooLarge(ApiError):
    status, default_code = 413, "too_large"


class UnsupportedMedia(ApiError):
    status, default_code = 415, "unsupported_media"


class InvalidInput(ApiError):
    status, default_code = 422, "invalid_input"


class TooManyJobs(ApiError):
    status, default_code = 429, "too_many_jobs"


class ServiceUnavailable(ApiError):
    status, default_code = 503, "unavailable"


def error_response(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    body = ErrorBody(error=ErrorDetail(code=code, message=message))
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


def describe_validation_errors(errors) -> str:
    """pydantic/FastAPI error list -> "field.path: message; ..." (names the offending fields)."""
    parts = []
    for err in errors:
        loc = [str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path", "header")]
        where = ".".join(loc) or "request"
        parts.append(f"{where}: {err.get('msg', 'invalid')}")
    return "; ".join(parts)


_HTTP_CODES = {404: "not_found", 405: "method_not_allowed", 401: "unauthorized", 413: "too_large"}


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_request: Request, exc: ApiError):
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError):
        return error_response(422, "invalid_request", describe_validation_errors(exc.errors()))

    @app.exception_handler(StarletteHTTPException)
    async def _http(_request: Request, exc: StarletteHTTPException):
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        return error_response(exc.status_code, code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal_error", "internal server error (logged on the server)")
