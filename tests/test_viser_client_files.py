"""viser's client served by the workbench as cacheable files: gzip when asked, validators, the same code.

The page of a session's 3D view (``/viser/{id}/``) links the client's script, styles and decoder under
``/viser-client/{digest}/``; those are decoded from viser's own single-file build, so what a browser
runs is byte for byte the script viser's loader would have decoded. That it still draws the map in
Chromium is checked in ``tests/browser/test_workbench.py``.
"""

from __future__ import annotations

import gzip
import re
import time
from collections.abc import Iterator
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest
import zstandard
from fastapi.testclient import TestClient

from app.routes import views
from app.server import create_app
from app.tokens import Role
from app.view.client_files import ViserClient, accepts_gzip, base88_decode, installed_client
from tests.session_fixtures import corridor_session

ALPHABET = b"!#$%()*+,-./0123456789:;=?@ABCDEFGHIJKLMNOPQRSTUVWXYZ[\\]^_abcdefghijklmnopqrstuvwxyz{|}~"
VISER_PAGE = files("viser").joinpath("client", "build", "index.html").read_bytes()


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=400, engine={"voxel_size": 0.2})
    with TestClient(create_app(root), base_url="http://127.0.0.1") as c:  # its shutdown stops the views
        yield c


def base88_encode(data: bytes) -> bytes:
    """The encoding viser's build uses (4 bytes -> 5 digits, big-endian; a tail of r bytes -> r + 1 digits)."""
    out = bytearray()
    whole = len(data) // 4 * 4
    for start in range(0, whole, 4):
        value = int.from_bytes(data[start : start + 4], "big")
        out += bytes(ALPHABET[(value // 88**k) % 88] for k in range(4, -1, -1))
    tail = data[whole:]
    if tail:
        value = int.from_bytes(tail, "big")
        out += bytes(ALPHABET[(value // 88**k) % 88] for k in range(len(tail), -1, -1))
    return bytes(out)


@pytest.mark.parametrize("size", [0, 1, 2, 3, 4, 5, 1001])
def test_base88_decoding_inverts_the_builds_encoding_including_a_short_tail(size: int) -> None:
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    assert base88_decode(base88_encode(data), ALPHABET) == data


def test_accept_encoding_is_read_as_browsers_and_proxies_write_it() -> None:
    assert accepts_gzip("gzip, deflate, br, zstd")
    assert accepts_gzip("br;q=1.0, gzip;q=0.8")
    assert accepts_gzip("*")
    assert not accepts_gzip("gzip;q=0, deflate")
    assert not accepts_gzip("identity")
    assert not accepts_gzip("")
    assert not accepts_gzip("gzip;q=oops")


def test_the_installed_build_splits_into_the_script_and_styles_vipers_loader_would_run() -> None:
    built = installed_client()
    assert built.split
    found = re.search(rb'data-ss="(\d+)" data-cs="(\d+)"', VISER_PAGE)
    assert found is not None
    style_bytes, script_bytes = int(found.group(1)), int(found.group(2))
    assert len(built.files["app.css"].body) == style_bytes and len(built.files["app.js"].body) == script_bytes
    assert b"__viserZstdWasm" in built.files["app.js"].body  # the client takes its decoder from the loader
    assert built.files["zstd.wasm"].body.startswith(b"\0asm")
    # the page keeps viser's head and loses only the encoded payload
    page = built.page
    assert b"data-p=" not in page and b"<title>Viser</title>" in page and b'<div id="root"></div>' in page
    assert len(page) < 10_000


def test_the_3d_client_is_answered_gzip_encoded_with_validators_and_cached_for_good(client: TestClient) -> None:
    page = client.get("/viser/corridor/", params={"websocket": "ws://127.0.0.1/viser/corridor"})
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert page.headers["cache-control"] == "no-store"  # its address is the view's own: never reused
    script = re.search(r'<link rel="modulepreload" href="(/viser-client/[0-9a-f]{16}/app\.js)">', page.text)
    assert script is not None, page.text[-600:]

    zipped = client.get(script.group(1), headers={"Accept-Encoding": "gzip"})
    assert zipped.status_code == 200 and zipped.headers["content-encoding"] == "gzip"
    assert zipped.headers["content-type"].startswith("text/javascript")
    assert "immutable" in zipped.headers["cache-control"] and zipped.headers["vary"] == "Accept-Encoding"
    assert zipped.num_bytes_downloaded < 0.4 * len(zipped.content)  # 2.5 MB of script, about a third on the wire
    plain = client.get(script.group(1), headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.content == zipped.content
    assert plain.headers["etag"] == zipped.headers["etag"]
    held = client.get(script.group(1), headers={"If-None-Match": f'W/{zipped.headers["etag"]}, "other"'})
    assert held.status_code == 304 and held.content == b""

    # byte for byte what viser's own loader decodes from its page
    payload = re.search(rb'<script data-p="([^"]*)" data-ss="(\d+)" data-cs="(\d+)">', VISER_PAGE)
    assert payload is not None
    style_bytes, script_bytes = int(payload.group(2)), int(payload.group(3))
    decoded = zstandard.ZstdDecompressor().decompress(
        base88_decode(payload.group(1), ALPHABET), max_output_size=style_bytes + script_bytes
    )
    assert plain.content == decoded[style_bytes:]
    styles = client.get(script.group(1).replace("app.js", "app.css"), headers={"Accept-Encoding": "gzip"})
    assert styles.headers["content-type"].startswith("text/css") and styles.content == decoded[:style_bytes]
    wasm = client.get(script.group(1).replace("app.js", "zstd.wasm"))
    assert wasm.headers["content-type"] == "application/wasm" and wasm.content.startswith(b"\0asm")

    stale = client.get(re.sub("/[0-9a-f]{16}/", "/0000000000000000/", script.group(1)))
    assert stale.status_code == 404 and "viser build" in stale.text


def test_the_page_is_answered_while_the_view_starts_and_an_unknown_session_is_refused(client: TestClient) -> None:
    registry = client.app.state.viewers  # type: ignore[attr-defined]
    assert client.get("/sessions/corridor").status_code == 200
    deadline = time.monotonic() + 30
    while registry.existing("corridor") is None:  # started in the background for the page's 3D view
        assert time.monotonic() < deadline, "the session page did not start its view"
        time.sleep(0.05)
    assert registry.existing("corridor").ready.wait(30)
    assert client.get("/viser/nowhere/").status_code == 404
    assert client.get("/sessions/nowhere").status_code == 404


def test_a_build_in_another_form_is_forwarded_from_the_views_own_server(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    other = ViserClient(b"<!doctype html><html><head><script>start()</script></head><body></body></html>")
    assert not other.split and other.files == {} and other.page == other.original
    monkeypatch.setattr(views, "installed_client", lambda: other)
    page = client.get("/viser/corridor/")
    assert page.status_code == 200 and b"data-p=" in page.content  # viser's own single-file page, as it serves it
    assert client.get(f"/viser-client/{other.digest}/app.js").status_code == 404


def test_a_build_whose_payload_does_not_decode_is_not_split() -> None:
    broken = re.sub(rb'data-p="[^"]{20}', b'data-p="' + b"!" * 20, VISER_PAGE, count=1)
    assert not ViserClient(broken).split
    assert ViserClient(gzip.compress(b"not a page")).files == {}


def test_on_a_shared_server_any_sessions_token_fetches_the_client_and_no_token_does_not(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=400, engine={"voxel_size": 0.2})
    with TestClient(create_app(root, require_token=True), base_url="http://127.0.0.1") as shared:
        secret, _ = shared.app.state.tokens.issue(Role.viewer, "corridor", name="vic")  # type: ignore[attr-defined]
        script = f"/viser-client/{installed_client().digest}/app.js"
        assert shared.get(script).status_code == 401
        fetched = shared.get(script, headers={"Authorization": f"Bearer {secret}"})
        assert fetched.status_code == 200 and fetched.content == installed_client().files["app.js"].body
