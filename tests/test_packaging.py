"""The project installs: a wheel built from the committed tree holds the web pages, and the
``slam6d-workbench`` it installs serves them from any working directory.

Built from ``git archive HEAD`` (a clean checkout: nothing untracked or uncommitted can hide a
missing file), with the environment's own setuptools (``--no-build-isolation``: no download), installed
with ``--target`` into an empty folder that goes first on ``PYTHONPATH``, and started from another
folder.
"""

from __future__ import annotations

import io
import os
import shutil
import socket
import subprocess
import sys
import tarfile
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from tests.conftest import PROJECT_ROOT
from tests.session_fixtures import corridor_session

pytestmark = pytest.mark.slow  # builds and installs a wheel, then starts a server: ~30 s


def _clean_checkout(into: Path) -> Path:
    if shutil.which("git") is None or not (PROJECT_ROOT / ".git").exists():
        message = "the packaging test builds from `git archive HEAD` and needs a git checkout"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " (required under CI=true)")
        pytest.skip(message)
    archive = subprocess.run(["git", "archive", "HEAD"], cwd=PROJECT_ROOT, capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    return into


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_the_wheel_holds_the_pages_and_the_installed_workbench_serves_them(tmp_path):
    source = _clean_checkout(tmp_path / "checkout")
    build = ["wheel", "--quiet", "--no-deps", "--no-build-isolation", "--wheel-dir", str(tmp_path / "dist")]
    subprocess.run([sys.executable, "-m", "pip", *build, str(source)], check=True, cwd=tmp_path)
    (wheel,) = (tmp_path / "dist").glob("slam6d_workbench-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for page in ("index.html", "session.html", "common.js", "style.css"):
        assert f"app/static/{page}" in names, names

    target = tmp_path / "installed"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), str(wheel)],
        check=True,
        cwd=tmp_path,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    sessions = tmp_path / "sessions"
    corridor_session(sessions, scans=3, points=500)
    env = {**os.environ, "PYTHONPATH": str(target)}  # the installed copy, not this checkout
    where = subprocess.run(
        [sys.executable, "-c", "import app; print(app.__file__)"],
        env=env,
        cwd=elsewhere,
        capture_output=True,
        text=True,
    )
    assert Path(where.stdout.strip()).is_relative_to(target), where.stdout + where.stderr

    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "app.main", "--sessions-dir", str(sessions), "--port", str(port)],
        env=env,
        cwd=elsewhere,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                landing = httpx.get(f"{base}/", timeout=5)
                break
            except httpx.TransportError:
                assert server.poll() is None and time.monotonic() < deadline, "the installed workbench did not start"
                time.sleep(0.3)
        assert landing.status_code == 200 and "<title>slam6d workbench</title>" in landing.text
        page = httpx.get(f"{base}/sessions/corridor", timeout=30)
        assert page.status_code == 200 and 'id="viewer"' in page.text
        assert httpx.get(f"{base}/static/common.js", timeout=5).status_code == 200
        docs = httpx.get(f"{base}/docs", timeout=5)
        assert docs.status_code == 200 and "swagger" in docs.text.lower()
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
