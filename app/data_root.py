"""Where sessions over server folders may read from: the data root.

A session can be created over a folder that already lives on the server (``POST /api/sessions``
with a ``source`` path). On a shared server that would let anyone read any file the server can,
so such sources must lie inside the folder the operator named with ``--data-root``; a server
bound off loopback without a data root refuses them altogether (uploads still work). The check
runs before anything looks at the path, and its refusal never says whether the path exists.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from app.errors import WorkbenchError


class SourceRefusedError(WorkbenchError):
    """A session source outside the data root (HTTP 403)."""

    default_status = 403


@dataclass(frozen=True)
class DataRoot:
    """``folder`` None: no data root; then folder sources are allowed only when ``shared`` is False."""

    folder: Path | None
    shared: bool

    def check(self, source: str | Path) -> Path:
        """The absolute source path (relative ones are taken inside the root), or SourceRefusedError."""
        path = Path(source).expanduser()
        if self.folder is None:
            if self.shared:
                raise SourceRefusedError(
                    "sessions over server folders are disabled on a shared server without --data-root; upload the scans"
                )
            return path.resolve()
        root = self.folder.expanduser().resolve()
        resolved = (root / path).resolve()  # an absolute path replaces root; symlinks and '..' are followed
        if not resolved.is_relative_to(root):
            raise SourceRefusedError(f"the source must lie inside the server's data root ({root.name}/)")
        return resolved

    def locate(self, recorded: str) -> Path | None:
        """Where a bundle's recorded scan source may be looked for here (``slam6d.bundle.SourceFinder``),
        or None: a path inside the exporter's data root is taken inside this one, an absolute path only
        where :meth:`check` allows it (anywhere on a loopback server without a data root)."""
        if not Path(recorded).is_absolute() and self.folder is None:
            return None  # relative to a data root this server does not have
        try:
            return self.check(recorded)
        except SourceRefusedError:
            return None


__all__ = ["DataRoot", "SourceRefusedError"]
