"""The FastAPI application: pages, REST, and the 3D views of viser, all behind one port.

Viser runs its own websocket server per session on an internal localhost port; this app forwards
``/viser/{session}/`` (the viser client page) and the websocket ``/viser/{session}`` to it, so a
user shares one URL and only one port is opened. The pages and their scripts are package data
(``app/static``), found through :mod:`importlib.resources`, so an installed wheel serves them from
any working directory.
"""

from __future__ import annotations

import inspect
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from app.routes import API_ROUTERS
from app.routes.dependencies import REQUIRE_SESSION
from app.routes.errors import install_error_handlers
from app.workbench import Workbench


def static_dir() -> Path:
    """The folder of the web pages inside the installed package (setuptools installs it as real files)."""
    folder = files("app").joinpath("static")
    if not isinstance(folder, Path) or not (folder / "index.html").is_file():
        raise RuntimeError(f"the workbench's web pages are missing from the installed package ({folder})")
    return folder


def create_app(sessions_dir: Path | str, viewers: bool = True, max_upload_mb: int = 512) -> FastAPI:
    """``viewers=False`` leaves out the 3D views (REST-only tests need no viser servers)."""
    workbench = Workbench(sessions_dir, max_upload_bytes=max_upload_mb * 1024 * 1024)
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
    app.state.on_shutdown = []
    install_error_handlers(app)
    for router in API_ROUTERS:
        app.include_router(router)

    if viewers:
        import httpx

        from app.routes import views
        from app.view.registry import ViewerRegistry

        registry = ViewerRegistry(workbench)
        app.state.viewers = registry
        app.state.viser_client = httpx.AsyncClient(timeout=30)
        app.include_router(views.router)
        app.state.on_shutdown.append(registry.stop_all)
        app.state.on_shutdown.append(app.state.viser_client.aclose)

    app.mount("/static", StaticFiles(directory=pages), name="static")

    @app.get("/", include_in_schema=False)
    def landing() -> FileResponse:
        return FileResponse(pages / "index.html")

    @app.get("/sessions/{session_id}", include_in_schema=False, dependencies=[REQUIRE_SESSION])
    def session_page(session_id: str) -> FileResponse:
        if viewers:  # start reading scans while the browser still loads the page and the 3D client
            app.state.viewers.get(session_id)
        return FileResponse(pages / "session.html")

    @app.get("/sessions", include_in_schema=False)
    def sessions_redirect() -> RedirectResponse:
        return RedirectResponse("/")

    return app
