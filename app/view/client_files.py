"""viser's browser client, served by the workbench itself as files a browser caches and compiles ahead.

viser ships its client as one page (``client/build/index.html``, what each view's own server
answers): the styles and a 2.5 MB script, zstd-compressed and base-88 encoded in a data attribute,
which a loader in the page decodes with a WebAssembly zstd decoder and then runs as an inline
module. Loaded that way the script is never cached (each session page's 3D view has an address of
its own, carrying its view key), it cannot be compiled while it downloads, and the page's main
thread first decodes 0.8 MB of text. The same build is decoded here once per server process into

* ``/viser-client/{digest}/app.js``, ``app.css``, ``zstd.wasm``: immutable (the digest names the
  build), gzip-encoded for a browser that accepts it, with an ETag;
* a page for ``/viser/{session}/`` (2 kB, not stored: its address carries the view key, so no
  browser could reuse it) that keeps viser's head and, instead of the encoded payload,
  links the styles, preloads the script (``modulepreload``: fetched and compiled in parallel,
  from the browser's cache on any later open of any session) and runs a short loader that compiles
  the zstd decoder first - the client decodes its websocket messages with it and finds it where
  viser's own loader leaves it, ``globalThis.__viserZstdWasm`` - and then imports the script.

Only the files viser installed are read; nothing of viser's Python API is touched. A build that is
not in that form (another viser release) is not split: its page is then forwarded from the view's
own server as it is (:func:`app.view.proxy.forward_file`).
"""

from __future__ import annotations

import gzip
import hashlib
import re
import threading
from dataclasses import dataclass
from importlib.resources import files

import numpy as np
import zstandard
from starlette.requests import Request
from starlette.responses import Response

CLIENT_PREFIX = "/viser-client"
IMMUTABLE = "public, max-age=31536000, immutable"  # the digest in the address changes with the build
PAGE_CACHE = "no-store"  # the page: one address per view key, never asked for twice

# viser's loader: <script data-p="PAYLOAD" data-ss="STYLE BYTES" data-cs="SCRIPT BYTES">(loader)</script>
_PAYLOAD = re.compile(rb'<script data-p="([^"]*)" data-ss="(\d+)" data-cs="(\d+)">(.*?)</script>', re.S)
_ALPHABET = re.compile(rb'const A="((?:[^"\\]|\\.)*)"')
_DECODER = re.compile(rb'const gzWasm="((?:[^"\\]|\\.)*)"')


@dataclass(frozen=True)
class ClientFile:
    """One file as sent: its bytes, their gzip encoding (made once), type, validator and cache policy."""

    body: bytes
    gzipped: bytes
    media_type: str
    etag: str
    cache_control: str

    @classmethod
    def of(cls, body: bytes, media_type: str, cache_control: str) -> ClientFile:
        etag = '"' + hashlib.sha256(body).hexdigest()[:32] + '"'
        return cls(body, gzip.compress(body, 6, mtime=0), media_type, etag, cache_control)

    def response(self, request: Request) -> Response:
        """304 when the browser holds this version (``If-None-Match``), else the file - gzip-encoded when
        the request accepts gzip."""
        headers = {"ETag": self.etag, "Cache-Control": self.cache_control, "Vary": "Accept-Encoding"}
        held = request.headers.get("if-none-match", "")
        if self.etag in (tag.strip().removeprefix("W/") for tag in held.split(",")) or held.strip() == "*":
            return Response(status_code=304, headers=headers)
        if accepts_gzip(request.headers.get("accept-encoding", "")):
            return Response(self.gzipped, media_type=self.media_type, headers={**headers, "Content-Encoding": "gzip"})
        return Response(self.body, media_type=self.media_type, headers=headers)


def accepts_gzip(accept_encoding: str) -> bool:
    """Whether an ``Accept-Encoding`` header takes gzip (named, or ``*``, and not with ``q=0``)."""
    for item in accept_encoding.lower().split(","):
        name, _, params = item.partition(";")
        if name.strip() not in ("gzip", "*"):
            continue
        quality = params.strip()
        if not quality.startswith("q="):
            return True
        try:
            return float(quality[2:]) > 0.0
        except ValueError:
            return False
    return False


def base88_decode(text: bytes, alphabet: bytes) -> bytes:
    """viser's base-88 text back to bytes: each 5 characters are 4 bytes (big-endian), a tail of r
    characters r - 1 bytes - the inverse of the encoding its loader undoes in the browser."""
    lookup = np.zeros(256, np.int64)
    lookup[np.frombuffer(alphabet, np.uint8)] = np.arange(len(alphabet))
    digits = lookup[np.frombuffer(text, np.uint8)]
    whole, rest = divmod(len(digits), 5)
    value = np.zeros(whole, np.int64)
    for column in range(5):
        value = value * 88 + digits[column : whole * 5 : 5]
    out = np.stack([(value >> shift) & 255 for shift in (24, 16, 8, 0)], axis=1).astype(np.uint8).tobytes()
    if rest:
        tail = 0
        for digit in digits[whole * 5 :]:
            tail = tail * 88 + int(digit)
        out += tail.to_bytes(rest - 1, "big")
    return out


class ViserClient:
    """The installed viser build, split into cacheable files (``split`` False: not in a form known here)."""

    def __init__(self, page: bytes) -> None:
        self.original = page
        self.page = page  # the page to serve in place of viser's: the same when not split
        self.files: dict[str, ClientFile] = {}
        self.digest = hashlib.sha256(page).hexdigest()[:16]
        found = _PAYLOAD.search(page)
        alphabet = None if found is None else _ALPHABET.search(found.group(4))
        decoder = None if found is None else _DECODER.search(found.group(4))
        if found is None or alphabet is None or decoder is None:
            return
        letters = alphabet.group(1).replace(b"\\\\", b"\\")
        style_bytes, script_bytes = int(found.group(2)), int(found.group(3))
        try:
            packed = base88_decode(found.group(1), letters)
            both = zstandard.ZstdDecompressor().decompress(packed, max_output_size=style_bytes + script_bytes)
            wasm = gzip.decompress(base88_decode(decoder.group(1).replace(b"\\\\", b"\\"), letters))
        except (zstandard.ZstdError, OSError, EOFError, ValueError):
            return
        if len(both) != style_bytes + script_bytes or not wasm.startswith(b"\0asm"):
            return
        self.files = {
            "app.css": ClientFile.of(both[:style_bytes], "text/css; charset=utf-8", IMMUTABLE),
            "app.js": ClientFile.of(both[style_bytes:], "text/javascript; charset=utf-8", IMMUTABLE),
            "zstd.wasm": ClientFile.of(wasm, "application/wasm", IMMUTABLE),
        }
        base = f"{CLIENT_PREFIX}/{self.digest}"
        loader = (
            f'<link rel="stylesheet" href="{base}/app.css">'
            f'<link rel="modulepreload" href="{base}/app.js">'
            '<script type="module">'
            f'globalThis.__viserZstdWasm = await WebAssembly.compileStreaming(fetch("{base}/zstd.wasm"));'
            f'await import("{base}/app.js");'
            "</script>"
        ).encode()
        self.page = page[: found.start()] + loader + page[found.end() :]

    @property
    def split(self) -> bool:
        return bool(self.files)

    def page_response(self) -> Response:
        return Response(self.page, media_type="text/html; charset=utf-8", headers={"Cache-Control": PAGE_CACHE})


_installed: ViserClient | None = None
_installed_lock = threading.Lock()


def installed_client() -> ViserClient:
    """The installed viser's client, decoded on first use (~0.1 s) and kept for the process."""
    global _installed
    with _installed_lock:
        if _installed is None:
            _installed = ViserClient(files("viser").joinpath("client", "build", "index.html").read_bytes())
        return _installed


def prepare_in_background() -> None:
    """Decode and compress the client off the request path, as the server starts."""
    threading.Thread(target=installed_client, name="viser-client-files", daemon=True).start()
