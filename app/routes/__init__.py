"""The REST API and the 3D view routes, one router per resource.

==================  =========================================================
module              resource
==================  =========================================================
``sessions``        sessions: list, create, upload, details, journal, undo/redo
``events``          a session's head pushed to its pages as it moves (websocket)
``bundles``         a session's whole history as a zip, and importing one
``exports``         poses per revision, pose and map downloads
``jobs``            background jobs: start registration/reload, poll, cancel
``loops``           loop hypotheses: detect, accept, reject; loop closing
``edges``           the pose graph by hand: edges, moving a scan
``relaxation``      relaxation jobs, residuals, displacement between revisions
``components``      the connected components a relaxation would see, the last failed run
``guesses``         octree guesses and ICP from a candidate
``traces``          stored traces of registration runs
``camera_path``     fly-through keyframes, render jobs, rendered videos
``comments``        comments anchored to a scan point, an edge or a loop
``links``           permalinks: a page link's revision, camera, selection and colour checked
``sharing``         who am I, a session's share links (owners)
``views``           each session's 3D view (viser) behind the same port
==================  =========================================================

Session lookup and the author header are FastAPI dependencies (:mod:`app.routes.dependencies`);
errors become statuses in one place (:mod:`app.routes.errors`).
"""

from __future__ import annotations

from fastapi import APIRouter

from app.routes import (
    bundles,
    camera_path,
    comments,
    components,
    edges,
    events,
    exports,
    guesses,
    jobs,
    links,
    loops,
    relaxation,
    sessions,
    traces,
)

API_ROUTERS: tuple[APIRouter, ...] = (
    sessions.router,
    events.router,
    bundles.router,
    exports.router,
    jobs.router,
    loops.router,
    edges.router,
    relaxation.router,
    components.router,
    guesses.router,
    traces.router,
    camera_path.router,
    comments.router,
    links.router,
)
