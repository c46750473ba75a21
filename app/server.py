"""The FastAPI application: pages, REST, and the 3D views of viser, all behind one port.

Viser runs its own websocket server per session on an internal localhost port; this app forwards
the websocket ``/viser/{session}`` to it and serves viser's browser client itself (``/viser/{session}/``
and the cacheable ``/viser-client/`` files, :mod:`app.view.client_files`), so a user shares one URL
and only one port is opened. The pages and their scripts are package data
(``app/static``), found through :mod:`importlib.resources`, so an installed wheel serves them from
any working directory.
"""

from __future__ import annotations

import inspect
from collections.abc import AsyncIterator, Iterable
from contextlib import asynccontextmanager
from importlib.resources import files
from pathlib import Path
from typing import Any

from anyio import open_file  # noqa: F401 - see the note below
from fastapi import Depends, FastAPI, Request
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from app.data_root import DataRoot
from app.editing import editor_for
from app.errors import UnknownSessionError
from app.guard import (
    GUARD_RESPONSES,
    GuardPolicy,
    RequestGuard,
    authorize,
    is_loopback,
    server_names,
    session_from_path,
)
from app.limits import RequestLimits
from app.permalink import LINK_PARAMETERS, parse_link, resolve_link
from app.resources import ResourceLimits
from app.revision_events import RevisionEvents
from app.revisions import REVISION_RESPONSES, RevisionHeaders, add_revision_errors, check_revision
from app.routes import API_ROUTERS
from app.routes.dependencies import SessionDep
from app.routes.errors import document_errors, install_error_handlers
from app.routes.sharing import build_sharing_router
from app.tokens import TokenStore
from app.workbench import Workbench
from slam6d.errors import Slam6dError
from slam6d.journal import Journal

UPLOAD_PATHS = ("/api/sessions/upload", "/api/sessions/import")  # multipart: streamed, bounded by the upload limit


# anyio imports its file module lazily, on the first FileResponse. Done then, in a worker thread
# while other threads compile code, CPython 3.11 can fail the import ("AST constructor recursion
# depth mismatch") and the first page of a fresh process answered 500; importing it here, once,
# on the main thread avoids that.


def static_dir() -> Path:
    """The folder of the web pages inside the installed package (setuptools installs it as real files)."""
    folder = files("app").joinpath("static")
    if not isinstance(folder, Path) or not (folder / "index.html").is_file():
        raise RuntimeError(f"the workbench's web pages are missing from the installed package ({folder})")
    return folder


def create_app(
    sessions_dir: Path | str,
    viewers: bool = True,
    max_upload_mb: int = 512,
    bind_host: str = "127.0.0.1",
    require_token: bool | None = None,
    data_root: Path | None = None,
    names: Iterable[str] = (),
    limits: ResourceLimits | None = None,
    scheduler: str | None = None,
) -> FastAPI:
    """``viewers=False`` leaves out the 3D views (REST-only tests need no viser servers).

    ``bind_host`` is the address the server listens on: off loopback, tokens are required (unless
    ``require_token`` says otherwise) and folder sessions only come from ``data_root``. ``limits``
    bounds running jobs, opened sessions' memory, idle 3D views and parse time. ``scheduler``
    (``local:N`` or ``tcp://HOST:PORT``): where registration and relaxation jobs run their parallel
    stages (:meth:`app.workbench.Workbench.scheduler`).
    """
    shared = not is_loopback(bind_host)
    workbench = Workbench(
        sessions_dir,
        max_upload_bytes=max_upload_mb * 1024 * 1024,
        data_root=DataRoot(data_root, shared),
        limits=limits,
        scheduler=scheduler,
    )
    pages = static_dir()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        for callback in app.state.on_shutdown:
            result = callback()
            if inspect.isawaitable(result):
                await result

    app = FastAPI(
        lifespan=lifespan,
        title="slam6d workbench",
        description="Sessions, pose revisions, exports and background jobs of the 6D SLAM workbench.",
        version="0.1.0",
    )
    app.state.workbench = workbench
    # before the 3D views listen: a page learns of a new head no later than its 3D view shows it
    app.state.revision_events = RevisionEvents(workbench)
    app.state.on_shutdown = [workbench.close_scheduler]
    install_error_handlers(app)
    app.add_middleware(
        RequestLimits,
        upload_limit=workbench.max_upload_bytes + (1 << 20),  # room for the multipart framing
        upload_paths=UPLOAD_PATHS,
    )
    # before any route is added: every route gets the guard's dependencies; the guard's middleware
    # is added last, so it is the outermost and nothing (not even a size refusal) answers before it
    app.router.dependencies.extend(
        add_guards(app, workbench, bind_host, shared if require_token is None else require_token, names)
    )
    for router in API_ROUTERS:
        app.include_router(router)
    app.include_router(build_sharing_router(app.state.tokens))  # who am I, share links
    document_errors(app)

    if viewers:
        import httpx

        from app.routes import views
        from app.view.client_files import prepare_in_background
        from app.view.registry import ViewerRegistry

        prepare_in_background()  # the 3D client's files, decoded and compressed once, off the request path
        from app.view.revision_view import RevisionViews

        registry = ViewerRegistry(workbench)
        app.state.viewers = registry
        app.state.revision_views = RevisionViews(workbench)  # older revisions opened from permalinks
        app.state.on_shutdown.append(app.state.revision_views.stop_all)
        app.state.viser_client = httpx.AsyncClient(timeout=30)
        app.include_router(views.router)
        app.state.on_shutdown.append(registry.stop_all)
        app.state.on_shutdown.append(app.state.viser_client.aclose)

    app.mount("/static", StaticFiles(directory=pages), name="static")

    @app.get("/", include_in_schema=False)
    def landing() -> FileResponse:
        return FileResponse(pages / "index.html")

    @app.get("/sessions/{session_id}", include_in_schema=False)
    def session_page(session_id: str, request: Request, state: SessionDep) -> FileResponse:
        # a permalink's parameters are checked before the page is served (422 naming the parameter)
        link = {k: v for k, v in request.query_params.items() if k in LINK_PARAMETERS}
        resolve_link(state, editor_for(workbench), parse_link(link))
        if viewers:  # start reading scans while the browser still loads the page and the 3D client
            app.state.viewers.start(session_id)
        return FileResponse(pages / "session.html")

    @app.get("/sessions", include_in_schema=False)
    def sessions_redirect() -> RedirectResponse:
        return RedirectResponse("/")

    return app


def add_guards(
    app: FastAPI, workbench: Workbench, bind_host: str, require_token: bool, names: Iterable[str]
) -> list[Any]:
    """The request guard (host, origin, token) in front of the revision headers (ETag); returns the
    dependencies every route needs (role and body type, then If-Match)."""
    tokens = TokenStore(workbench.sessions_dir)
    app.state.tokens = tokens

    def session_of(path_params: dict[str, Any]) -> str | None:
        job_id = path_params.get("job_id")
        if job_id is not None:  # a job acts on its session; an unknown job on none (answered 404 later)
            job = workbench.jobs.get(str(job_id))
            return None if job is None else job.session_id
        return session_from_path(path_params)

    def journal_of(session_id: str) -> Journal | None:
        try:
            return workbench.state(session_id).session.journal
        except (UnknownSessionError, Slam6dError):
            return None

    policy = GuardPolicy(tokens, require_token, server_names(bind_host, names), session_of)
    app.router.responses.update({**GUARD_RESPONSES, **REVISION_RESPONSES})  # in every route's OpenAPI
    add_revision_errors(app)
    app.add_middleware(RevisionHeaders, journal_of=journal_of)
    app.add_middleware(RequestGuard, policy=policy)  # outermost: nothing is answered before it
    return [Depends(authorize(policy)), Depends(check_revision(journal_of))]
