"""The FastAPI application: pages, REST, and the 3D views of viser, all behind one port.

Viser runs its own websocket server per session on an internal localhost port; this app forwards
``/viser/{session}/`` (the viser client page) and the websocket ``/viser/{session}`` to it, so a
user shares one URL and only one port is opened.
"""

from __future__ import annotations

import inspect
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, HTTPException
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from app.api import build_router
from app.edit_api import build_edit_router
from app.render_panel import build_render_router
from app.workbench import UnknownSessionError, Workbench

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"


def create_app(sessions_dir: Path | str, viewers: bool = True, max_upload_mb: int = 512) -> FastAPI:
    """``viewers=False`` leaves out the 3D views (REST-only tests need no viser servers)."""
    workbench = Workbench(sessions_dir, max_upload_bytes=max_upload_mb * 1024 * 1024)

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
    app.state.on_shutdown = []
    app.include_router(build_router(workbench))
    app.include_router(build_edit_router(workbench))  # loops, edges, moves, relaxation, guesses, traces
    app.include_router(build_render_router(workbench))  # fly-through: camera path, render jobs, downloads

    if viewers:
        from app.proxy import add_view_status_route, add_viewer_routes
        from app.viewer import ViewerRegistry

        registry = ViewerRegistry(workbench)
        app.state.viewers = registry
        add_viewer_routes(app, registry)
        add_view_status_route(app, registry)
        app.state.on_shutdown.append(registry.stop_all)

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def landing() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/sessions/{session_id}", include_in_schema=False)
    def session_page(session_id: str) -> FileResponse:
        try:
            workbench.state(session_id)
        except UnknownSessionError:
            raise HTTPException(404, f"no session '{session_id}'") from None
        if viewers:  # start reading scans while the browser still loads the page and the 3D client
            app.state.viewers.get(session_id)
        return FileResponse(STATIC_DIR / "session.html")

    @app.get("/sessions", include_in_schema=False)
    def sessions_redirect() -> RedirectResponse:
        return RedirectResponse("/")

    return app
