"""Access tokens: who may do what on a shared workbench.

A token is a random secret handed to one person (a share link or the ``slam6d-workbench token``
command). The server keeps only its SHA-256, so a copy of the sessions folder (or of this
database) does not let anyone in, and a secret is never written anywhere after it was printed
once. Each token carries a role - ``viewer`` (look, export) < ``reviewer`` (+ comments, accept or
reject loops) < ``editor`` (+ every edit and job) < ``owner`` (+ tokens, deleting) - and is valid
either on the whole server or on one session, until it expires or is revoked.

The store is one SQLite file in the sessions folder, beside the sessions it guards; every call
opens its own short connection, so the server's worker threads and the command line can share it.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import sqlite3
from contextlib import closing
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from enum import IntEnum
from pathlib import Path

from app.view.names import InvalidNameError, checked_name
from slam6d.errors import Slam6dError

TOKEN_DB = "access.sqlite"
_TOKEN_BYTES = 32
_DURATION = re.compile(r"^(\d+)([smhdw])$")
_UNITS = {"s": "seconds", "m": "minutes", "h": "hours", "d": "days", "w": "weeks"}


class Role(IntEnum):
    """Ordered: a role may do everything the roles below it may."""

    viewer = 1
    reviewer = 2
    editor = 3
    owner = 4

    @classmethod
    def parse(cls, name: str) -> Role:
        try:
            return cls[name]
        except KeyError:
            raise TokenError(f"unknown role '{name}'; known: {', '.join(r.name for r in cls)}") from None


class TokenError(Slam6dError):
    """A token request that cannot be met (unknown role, bad duration, unknown token id)."""


@dataclass(frozen=True)
class Grant:
    """What one token allows; never holds the secret itself."""

    id: str  # public handle for listing and revoking
    role: Role
    session: str | None  # None: every session of the server
    name: str  # who it was given to (shown in presence and as the journal's author)
    created: str
    expires: str | None
    revoked: bool

    def allows(self, role: Role, session: str | None) -> bool:
        """``role`` on ``session`` (None: a server-wide action such as creating a session)."""
        if self.role < role:
            return False
        return self.session is None or self.session == session

    def as_dict(self) -> dict[str, object]:
        return {
            "id": self.id,
            "role": self.role.name,
            "session": self.session,
            "name": self.name,
            "created": self.created,
            "expires": self.expires,
            "revoked": self.revoked,
        }


def parse_duration(text: str | None) -> timedelta | None:
    """``30m``, ``12h``, ``7d``, ``2w`` (or None / ``never``: no expiry)."""
    if text is None or text == "never":
        return None
    found = _DURATION.match(text.strip())
    if found is None or int(found.group(1)) == 0:
        raise TokenError(f"expiry '{text}' is not a duration like 30m, 12h, 7d or 2w (or 'never')")
    return timedelta(**{_UNITS[found.group(2)]: int(found.group(1))})


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8", "surrogatepass")).hexdigest()


def _now() -> datetime:
    return datetime.now(UTC)


class TokenStore:
    """The tokens of one server, stored hashed in ``<sessions>/access.sqlite``."""

    def __init__(self, sessions_dir: Path | str) -> None:
        self.path = Path(sessions_dir) / TOKEN_DB  # created with the first token: none issued, no file

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, timeout=30)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute(
            "CREATE TABLE IF NOT EXISTS tokens (id TEXT PRIMARY KEY, digest TEXT UNIQUE NOT NULL,"
            " role INTEGER NOT NULL, session TEXT, name TEXT NOT NULL, created TEXT NOT NULL,"
            " expires TEXT, revoked INTEGER NOT NULL DEFAULT 0)"
        )
        return conn

    def issue(
        self, role: Role, session: str | None = None, expires_in: timedelta | None = None, name: str = ""
    ) -> tuple[str, Grant]:
        """A new token: the secret (shown once, to hand over) and what it grants. ``name`` is who acts
        with it (journal, comments, presence): TokenError when it is not a valid name."""
        try:
            name = checked_name(name)
        except InvalidNameError as exc:
            raise TokenError(f"name: {exc}") from None
        secret = secrets.token_urlsafe(_TOKEN_BYTES)
        created = _now()
        grant = Grant(
            id=secrets.token_hex(6),
            role=role,
            session=session,
            name=name or role.name,
            created=created.isoformat(timespec="seconds"),
            expires=None if expires_in is None else (created + expires_in).isoformat(timespec="seconds"),
            revoked=False,
        )
        with closing(self._connect()) as conn, conn:
            conn.execute(
                "INSERT INTO tokens (id, digest, role, session, name, created, expires) VALUES (?,?,?,?,?,?,?)",
                (grant.id, _digest(secret), int(role), session, grant.name, grant.created, grant.expires),
            )
        return secret, grant

    def resolve(self, secret: str) -> Grant | None:
        """The grant of a valid token; None for an unknown, expired or revoked one."""
        if not self.path.exists():
            return None
        with closing(self._connect()) as conn:
            row = conn.execute(
                "SELECT id, role, session, name, created, expires, revoked FROM tokens WHERE digest=?",
                (_digest(secret),),
            ).fetchone()
        if row is None:
            return None
        grant = _grant(row)
        if grant.revoked or (grant.expires is not None and datetime.fromisoformat(grant.expires) <= _now()):
            return None
        return grant

    def revoke(self, token_id: str) -> Grant:
        with closing(self._connect()) as conn, conn:
            if conn.execute("UPDATE tokens SET revoked=1 WHERE id=?", (token_id,)).rowcount == 0:
                raise TokenError(f"no token with id '{token_id}'")
            row = conn.execute(
                "SELECT id, role, session, name, created, expires, revoked FROM tokens WHERE id=?", (token_id,)
            ).fetchone()
        return _grant(row)

    def grants(self, session: str | None = None) -> list[Grant]:
        """Every token (or those valid on ``session``: its own and the server-wide ones), oldest first."""
        if not self.path.exists():
            return []
        with closing(self._connect()) as conn:
            rows = conn.execute(
                "SELECT id, role, session, name, created, expires, revoked FROM tokens ORDER BY created, id"
            ).fetchall()
        found = [_grant(r) for r in rows]
        return found if session is None else [g for g in found if g.session in (None, session)]


def _grant(row: tuple[object, ...]) -> Grant:
    return Grant(
        id=str(row[0]),
        role=Role(int(row[1])),  # type: ignore[call-overload]
        session=None if row[2] is None else str(row[2]),
        name=str(row[3]),
        created=str(row[4]),
        expires=None if row[5] is None else str(row[5]),
        revoked=bool(row[6]),
    )


__all__ = ["TOKEN_DB", "Grant", "Role", "TokenError", "TokenStore", "parse_duration"]
