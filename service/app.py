"""The FastAPI application: `create_app(settings)`; `app` for `uvicorn service.app:app`."""
from __future__ import annotations

import functools
import importlib.util
import logging
from pathlib import Path
from typing import Callable

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

from jobs.jobfiles import job_files
from jobs.queue import make_celery
from jobs.sessions import SessionStore
from jobs.store import JobStore, connect
from service import openapi
from service.auth import KeyRing
from service.bodylimits import BodyLimits
from service.config import ServiceSettings
from service.context import AppContext
from service.errors import install_error_handlers
from service.fieldcache import FieldCache
from service.metrics import Metrics, MetricsMiddleware
from service.origin import OriginGuard
from service.routes import health, jobs, lightfield, sessions, ui
from service.session_versions import SessionVersionHeaders
from service.uploadcheck import UploadChecks

log = logging.getLogger("lightfield.service")
UI_DIR = Path(__file__).parent / "ui"
DOCS_ASSETS = "/docs-assets"

DESCRIPTION = """Spatiotemporally varying indoor HDR lighting as a service.

Upload an image or a video (`POST /jobs`), follow the job (`GET /jobs/{id}`, SSE at
`/jobs/{id}/events`), then query the light field: `GET /lightfield/{id}/envmap?x=X,Y,Z&t=SEC`.
Conventions (frames, equirect layout, tone map) are in every query response's
`X-Lightfield-Conventions` header. See docs/api.md."""


def create_app(settings: ServiceSettings | None = None,
               dependency_states: Callable[[], dict[str, str]] | None = None) -> FastAPI:
    """The API. `dependency_states` (embedded mode: the supervisor's) is what /healthz reports."""
    settings = settings or ServiceSettings.from_env()
    if not settings.broker_url:
        raise RuntimeError("LIGHTFIELD_BROKER_URL is not set (use `lightfield serve`, which starts Redis itself)")
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    store = JobStore(connect(settings.broker_url))
    keyring = KeyRing.parse(settings.api_keys)
    metrics = Metrics(store)
    ctx = AppContext(settings=settings, keyring=keyring, store=store, celery=make_celery(settings),
                     fields=FieldCache(settings.field_cache_size), metrics=metrics,
                     upload_checks=UploadChecks(settings.limits.upload_checks, settings.limits.upload_check_s),
                     files=job_files(settings), sessions=SessionStore(store.client))
    app = FastAPI(title="lightfield", version="0.1.0", description=DESCRIPTION, docs_url=None, redoc_url=None)
    install_offline_docs(app)
    app.state.ctx = ctx
    app.state.metrics = metrics
    app.state.dependency_states = dependency_states
    # outermost last: metrics see every answer, including the guards' refusals
    app.add_middleware(BodyLimits, max_json_bytes=settings.limits.max_json_bytes, timeouts=settings.timeouts)
    app.add_middleware(OriginGuard, keyless=not keyring.enabled, allowed_hosts=settings.allowed_hosts,
                       allowed_origins=settings.allowed_origins)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    app.add_middleware(SessionVersionHeaders)
    install_error_handlers(app)
    openapi.install(app, settings)
    for module in (jobs, sessions, lightfield, ui, health):
        app.include_router(module.router)
    if UI_DIR.is_dir():
        app.mount("/ui", StaticFiles(directory=UI_DIR, html=True), name="ui")

        @app.get("/", include_in_schema=False)
        def root():
            return RedirectResponse("/ui/")

    return app


def install_offline_docs(app: FastAPI) -> None:
    """/docs (Swagger UI) and /redoc served from the assets the `fastapi-offline` wheel ships,
    not from a CDN, so they work on machines without internet access."""
    assets = Path(importlib.util.find_spec("fastapi_offline").origin).parent / "static"
    app.mount(DOCS_ASSETS, StaticFiles(directory=assets), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui():
        return get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{app.title} - Swagger UI",
                                   oauth2_redirect_url=app.swagger_ui_oauth2_redirect_url,
                                   swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
                                   swagger_favicon_url=f"{DOCS_ASSETS}/favicon.png")

    @app.get(app.swagger_ui_oauth2_redirect_url, include_in_schema=False)
    def swagger_ui_redirect():
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    def redoc():
        return get_redoc_html(openapi_url=app.openapi_url, title=f"{app.title} - ReDoc",
                              redoc_js_url=f"{DOCS_ASSETS}/redoc.standalone.js",
                              redoc_favicon_url=f"{DOCS_ASSETS}/favicon.png", with_google_fonts=False)


@functools.lru_cache(maxsize=1)
def _app_from_env() -> FastAPI:
    return create_app()


def __getattr__(name: str):
    # `uvicorn service.app:app` builds the app from the environment on first access, so
    # importing this module (tests, `lightfield serve`) has no side effects.
    if name == "app":
        return _app_from_env()
    raise AttributeError(name)
