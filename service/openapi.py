"""The OpenAPI document states the limits THIS server enforces, read from its settings.

Some bounds are constants and live in the route signatures and models (x's format, |t|, ev,
the offset of GET /jobs). Others are configured per deployment (LIGHTFIELD_MAX_*), so the
generated schema is completed here: `maximum` on height, size and limit, `maxItems` on a
batch's queries, byte limits and accepted media types on the upload's parts. A client (or
schemathesis) reading /openapi.json then knows every size the server will refuse.
"""
from __future__ import annotations

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.config import ServiceSettings

IMAGE_TYPES = "image/png, image/jpeg, image/webp, image/bmp, image/tiff"
VIDEO_TYPES = "video/mp4, video/quicktime, video/x-matroska, video/webm, video/x-msvideo, image/gif"
DEPTH_TYPES = "application/x-npz, application/x-npy, image/x-exr, image/png"


def _set_parameter_maximum(operation: dict, name: str, maximum: int) -> None:
    for param in operation.get("parameters", []):
        if param.get("name") == name:
            param.setdefault("schema", {})["maximum"] = maximum


def complete_schema(schema: dict, settings: ServiceSettings) -> dict:
    limits = settings.limits
    paths = schema.get("paths", {})
    for path, methods in paths.items():
        for method, operation in methods.items():
            if not isinstance(operation, dict):
                continue
            if path.startswith("/lightfield/"):
                _set_parameter_maximum(operation, "height", limits.max_envmap_height)
                _set_parameter_maximum(operation, "size", limits.max_cubemap_size)
                _set_parameter_maximum(operation, "frames", limits.max_sequence_frames)
            if path == "/jobs" and method == "get":
                _set_parameter_maximum(operation, "limit", limits.max_page_size)
    schema.setdefault("components", {}).setdefault("securitySchemes", {})["HTTPBearer"] = {
        "type": "http", "scheme": "bearer", "description": "API key of a tenant (LIGHTFIELD_API_KEYS)"}
    for path, methods in paths.items():
        if path.startswith(("/jobs", "/lightfield")):
            for operation in methods.values():
                if isinstance(operation, dict):
                    operation["security"] = [{"HTTPBearer": []}]
    batch = schema.get("components", {}).get("schemas", {}).get("EnvmapBatchRequest")
    if batch:
        batch["properties"]["queries"]["maxItems"] = limits.max_batch
        batch["properties"]["height"]["maximum"] = limits.max_envmap_height
    upload = paths.get("/jobs", {}).get("post", {}).get("requestBody", {}).get("content", {}).get("multipart/form-data")
    if upload:
        props = upload["schema"]["properties"]
        props["file"]["description"] += f"; at most {limits.max_upload_bytes} bytes"
        props["depth"]["description"] += f"; at most {limits.max_depth_bytes} bytes"
        props["params"]["maxLength"] = limits.max_params_bytes
        upload["encoding"] = {"file": {"contentType": f"{IMAGE_TYPES}, {VIDEO_TYPES}"},
                              "depth": {"contentType": DEPTH_TYPES}, "params": {"contentType": "application/json"}}
    schema.setdefault("info", {})["x-lightfield-limits"] = {
        "json_body_bytes": limits.max_json_bytes,
        "upload_bytes": limits.max_upload_bytes,
        "depth_bytes": limits.max_depth_bytes,
        "params_bytes": limits.max_params_bytes,
        "jobs_in_flight_per_tenant": limits.max_jobs_in_flight,
        "header_timeout_s": settings.timeouts.header_s,
        "body_idle_timeout_s": settings.timeouts.body_idle_s,
        "body_min_rate_bytes_per_s": settings.timeouts.body_min_rate,
    }
    return schema


def install(app: FastAPI, settings: ServiceSettings) -> None:
    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            app.openapi_schema = complete_schema(schema, settings)
        return app.openapi_schema

    app.openapi = openapi
