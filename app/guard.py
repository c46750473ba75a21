"""Every request's door: the right host name, the server's own origin, a token with the right role.

Two pieces that every request passes, so a route added later is guarded without anyone
remembering to. :class:`RequestGuard`, an ASGI middleware in front of everything the server
answers (pages, REST, static files, the OpenAPI document, the viser websocket proxy), checks:

1. **Host** (DNS rebinding): a page on ``evil.example`` whose name later resolves to this machine
   would otherwise be "same origin" with us. IP literals and ``localhost`` are always accepted
   (a rebinding needs a name); other names only when the server was told them.
2. **Origin** of every state-changing request and of every websocket upgrade: a browser names the
   page that made the request in ``Origin`` (and ``Sec-Fetch-Site``); anything but this server is
   refused with 403.
3. **Token**: ``Authorization: Bearer T``, the ``slam6d_token`` cookie, or ``?token=T`` on a page
   link (answered with that cookie, HttpOnly and SameSite=Strict, so the page's own requests and
   websocket carry it and the page can drop it from its address). Without a valid token: 401 when
   tokens are required (the server is bound off loopback); a loopback server stays open to its
   one user.

Then :func:`authorize`, a dependency of every route (it needs the route the request reached):

4. **Role**: reading needs ``viewer``; a state-changing request needs ``editor`` unless its route
   declares another role (:func:`requires`, kept in the route's OpenAPI ``x-role``). A token made
   for one session is good on that session's pages, REST, jobs and 3D view only. 403 otherwise.
5. **Body type**: a POST must carry JSON (or, where the route takes a form, multipart): a
   cross-site form or ``fetch`` without a preflight cannot produce one.

The grant found is left in ``request.state.grant`` (the author's name, what the page may show)
and the session acted on in ``request.state.session``. Secrets are never logged nor echoed.

**One name per person.** ``grant.name`` is who acts, for the journal (routes take their author from
it, :data:`app.routes.dependencies.Author`), comments and presence alike: a token's holder is the
token's name, whatever the page claims; on an open loopback server it is the name typed in the page
header (sent as ``X-Author`` - percent-encoded UTF-8, so any script travels - and as the
``slam6d-author`` cookie, which the 3D view's websocket carries too). A name that is too long or
holds control characters is refused with 422 naming ``X-Author`` (:func:`app.view.names.checked_name`).
"""

from __future__ import annotations

import ipaddress
import json
import socket
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, replace
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from fastapi import HTTPException, WebSocketException, params
from fastapi.routing import APIRoute
from pydantic import BaseModel
from starlette.datastructures import Headers
from starlette.requests import HTTPConnection
from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.tokens import Grant, Role, TokenStore
from app.view.names import AUTHOR_COOKIE, InvalidNameError, name_from_cookie, name_from_header

TOKEN_COOKIE = "slam6d_token"
ROLE_KEY = "x-role"
ANY_SESSION_KEY = "x-any-session"
READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})

# The one user of a server open on loopback: may do everything, has no name of its own.
OPEN_GRANT = Grant(id="local", role=Role.owner, session=None, name="", created="", expires=None, revoked=False)


class Refusal(BaseModel):
    """What the guard answers when it refuses a request."""

    detail: str


# documented on every route: what any request may be answered by the guard
GUARD_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: {"model": Refusal, "description": "Host is not a name of this server (DNS rebinding)"},
    401: {"model": Refusal, "description": "no valid access token (a shared server)"},
    403: {"model": Refusal, "description": "the token's role or session does not allow this, or a cross-site request"},
    415: {"model": Refusal, "description": "a POST without a JSON (or, where taken, form) body"},
}


def is_open(grant: Grant) -> bool:
    """Whether ``grant`` is the open loopback server's (named or not), not a token's."""
    return grant.id == OPEN_GRANT.id


def open_grant(name: str) -> Grant:
    """The open server's grant under the name its user typed (presence and the journal show it)."""
    return replace(OPEN_GRANT, name=name) if name else OPEN_GRANT


def page_name(headers: Headers) -> str:
    """The name typed in a page: its ``X-Author`` (REST calls, scripts; GuardError 422 when it is not a
    valid name) or else its name cookie (the 3D view's websocket, plain page loads)."""
    header = headers.get("x-author")
    if header is not None and header.strip():
        try:
            return name_from_header(header)
        except InvalidNameError as exc:
            raise GuardError(422, str(exc), field=("header", "X-Author")) from None
    return name_from_cookie(cookie_value(headers, AUTHOR_COOKIE))


def cookie_value(headers: Headers, name: str) -> str | None:
    """One cookie's value (None when absent, empty, or the Cookie header is malformed - never an error)."""
    cookie = SimpleCookie()
    try:
        cookie.load(headers.get("cookie", ""))
    except Exception:
        return None
    found = cookie.get(name)
    return (found.value or None) if found is not None else None


def requires(role: Role, any_session: bool = False) -> dict[str, Any]:
    """``openapi_extra`` for a route that needs a role other than the default (viewer to read,
    editor to change); ``any_session``: a server-wide route open to a single session's token too."""
    return {ROLE_KEY: role.name, ANY_SESSION_KEY: True} if any_session else {ROLE_KEY: role.name}


def is_loopback(host: str) -> bool:
    """Whether binding to ``host`` keeps the server on this machine (then it may run without tokens)."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def server_names(bind_host: str, extra: Iterable[str] = ()) -> frozenset[str]:
    """Host names this server answers to besides IP literals: the bound name, the machine's names, ``extra``."""
    names = {n.lower() for n in extra} | set(LOOPBACK_NAMES)
    if bind_host:
        names.add(bind_host.lower())
    if not is_loopback(bind_host):  # shared on the network: teammates use the machine's own name
        names.update({socket.gethostname().lower(), socket.getfqdn().lower()})
    return frozenset(names)


class GuardError(Exception):
    """A refusal; ``field`` names the part of the request at fault (answered like FastAPI's own 422)."""

    def __init__(
        self, status: int, message: str, authenticate: bool = False, field: tuple[str, ...] | None = None
    ) -> None:
        self.status = status
        self.message = message
        self.authenticate = authenticate
        self.field = field
        super().__init__(message)

    def detail(self) -> str | list[dict[str, Any]]:
        if self.field is None:
            return self.message
        return [{"loc": list(self.field), "msg": self.message, "type": "value_error"}]


@dataclass(frozen=True)
class GuardPolicy:
    tokens: TokenStore
    require_token: bool
    host_names: frozenset[str]
    # the session a matched route acts on (its path parameters; e.g. a job's session), None if server-wide
    session_of: Callable[[dict[str, Any]], str | None]


def session_from_path(path_params: dict[str, Any]) -> str | None:
    value = path_params.get("session_id")
    return None if value is None else str(value)


class RequestGuard:
    """The ASGI middleware: host, origin and token of every request and websocket."""

    def __init__(self, app: ASGIApp, policy: GuardPolicy) -> None:
        self.app = app
        self.policy = policy

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        try:
            grant, from_query = self.admit(scope, headers)
        except GuardError as exc:
            await _refuse(scope, receive, send, exc)
            return
        scope.setdefault("state", {})["grant"] = grant
        if from_query is None or scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        secure = scope.get("scheme") == "https"

        async def send_with_cookie(message: Message) -> None:
            if message["type"] == "http.response.start":
                cookie = f"{TOKEN_COOKIE}={from_query}; HttpOnly; SameSite=Strict; Path=/" + (
                    "; Secure" if secure else ""
                )
                message = {**message, "headers": [*message.get("headers", []), (b"set-cookie", cookie.encode())]}
            await send(message)

        await self.app(scope, receive, send_with_cookie)

    def admit(self, scope: Scope, headers: Headers) -> tuple[Grant, str | None]:
        """The grant a request acts with and the token to set as cookie (if it came in the query); or GuardError."""
        check_host(headers, self.policy.host_names)
        if scope["type"] == "websocket" or str(scope["method"]).upper() not in READ_METHODS:
            check_origin(headers)
        secret, from_query = token_of(scope, headers)
        grant = self.policy.tokens.resolve(secret) if secret else None
        if secret and grant is None:
            raise GuardError(401, "the access token is unknown, expired or revoked", authenticate=True)
        if grant is None:
            if self.policy.require_token:
                raise GuardError(401, "this server needs an access token (ask the session's owner for a link)", True)
            grant = open_grant(page_name(headers))
        return grant, (secret if from_query else None)


def authorize(policy: GuardPolicy) -> Callable[[HTTPConnection], Awaitable[None]]:
    """The dependency checking role, session and body type of the route a request reached."""

    async def check(connection: HTTPConnection) -> None:
        grant: Grant = connection.scope.get("state", {}).get("grant", OPEN_GRANT)
        route = connection.scope.get("route")
        websocket = connection.scope["type"] == "websocket"
        method = "WEBSOCKET" if websocket else str(connection.scope["method"]).upper()
        role = required_role(route, method)
        session = policy.session_of(dict(connection.path_params))
        connection.state.session = session
        if session is None and (getattr(route, "openapi_extra", None) or {}).get(ANY_SESSION_KEY):
            session = grant.session
        if not grant.allows(role, session):
            where = f"session '{session}'" if session else "this server"
            message = f"a {grant.role.name} token may not do this on {where}; it needs {role.name}"
            if websocket:
                raise WebSocketException(code=1008, reason=message[:120])
            raise HTTPException(403, message)
        if method == "POST":
            check_body_type(Headers(scope=connection.scope), route)

    return check


def check_host(headers: Headers, names: frozenset[str]) -> None:
    host = headers.get("host", "")
    name = urlsplit(f"//{host}").hostname or ""
    if not name:
        raise GuardError(400, "the request has no Host header")
    try:
        ipaddress.ip_address(name)
        return
    except ValueError:
        pass
    if name.lower() not in names:
        raise GuardError(400, f"this server does not answer to the host name '{name[:100]}'")


def check_origin(headers: Headers) -> None:
    """A browser's request from another site (Origin or Sec-Fetch-Site say so) may not change anything."""
    fetch_site = headers.get("sec-fetch-site")
    if fetch_site is not None and fetch_site not in ("same-origin", "none"):
        raise GuardError(403, f"cross-site request refused (Sec-Fetch-Site: {fetch_site[:40]})")
    origin = headers.get("origin")
    if origin is None:
        return  # not a browser (a script, curl): nothing was forged on someone's behalf
    if urlsplit(origin).netloc.lower() != headers.get("host", "").lower() or origin == "null":
        raise GuardError(403, "cross-origin request refused: Origin is not this server")


def check_body_type(headers: Headers, route: BaseRoute | None) -> None:
    """POSTs carry JSON (or a form where the route takes one): a cross-site simple request cannot."""
    media = headers.get("content-type", "").split(";")[0].strip().lower()
    if media == "application/json":
        return
    if media in ("multipart/form-data", "application/x-www-form-urlencoded") and takes_form(route):
        return  # a form route: browsers' cross-site forms are stopped by the Origin check
    expected = "multipart/form-data" if takes_form(route) else "application/json (an empty body is {})"
    raise HTTPException(415, f"this request needs Content-Type {expected}")


def takes_form(route: BaseRoute | None) -> bool:
    return isinstance(route, APIRoute) and any(
        isinstance(p.field_info, params.Form) for p in route.dependant.body_params
    )


def required_role(route: BaseRoute | None, method: str) -> Role:
    declared = (getattr(route, "openapi_extra", None) or {}).get(ROLE_KEY)
    if declared is not None:
        return Role.parse(str(declared))
    return Role.viewer if method in READ_METHODS or method == "WEBSOCKET" else Role.editor


def token_of(scope: Scope, headers: Headers) -> tuple[str | None, bool]:
    """The secret a request carries and whether it came in the query (to be turned into a cookie)."""
    auth = headers.get("authorization", "")
    if auth[:7].lower() == "bearer " and auth[7:].strip():
        return auth[7:].strip(), False
    query = dict(parse_qsl(scope.get("query_string", b"").decode("latin-1")))
    if query.get("token"):
        return query["token"], True
    return cookie_value(headers, TOKEN_COOKIE), False


async def _refuse(scope: Scope, receive: Receive, send: Send, error: GuardError) -> None:
    if scope["type"] == "websocket":
        if "websocket.http.response" not in scope.get("extensions", {}):
            await send({"type": "websocket.close", "code": 4000 + error.status, "reason": error.message[:120]})
            return
        # the handshake is answered with a plain HTTP status (ASGI websocket denial response)
        await send(
            {
                "type": "websocket.http.response.start",
                "status": error.status,
                "headers": [(b"content-type", b"application/json")],
            }
        )
        await send({"type": "websocket.http.response.body", "body": json.dumps({"detail": error.detail()}).encode()})
        return
    headers = [(b"content-type", b"application/json")]
    if error.authenticate:
        headers.append((b"www-authenticate", b'Bearer realm="slam6d workbench"'))
    await send({"type": "http.response.start", "status": error.status, "headers": headers})
    await send({"type": "http.response.body", "body": json.dumps({"detail": error.detail()}).encode()})


__all__ = [
    "GUARD_RESPONSES",
    "OPEN_GRANT",
    "TOKEN_COOKIE",
    "GuardError",
    "GuardPolicy",
    "RequestGuard",
    "authorize",
    "is_loopback",
    "is_open",
    "open_grant",
    "page_name",
    "requires",
    "server_names",
    "session_from_path",
]
