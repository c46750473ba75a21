"""A reader that misbehaves on request, to show the fuzz harness reports each kind of failure.

It lives in a module of its own (not the test module) because the harness's worker process imports
the reader by name, and this module imports nothing heavy, so each restart of the worker is quick.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from slam6d.errors import FormatError


def misbehave(path: Path) -> None:
    """Do what the file says: ``ok``, ``refuse``, ``refuse anonymously``, ``raise``, ``hang``,
    ``allocate``, ``abort`` or ``abort after a failed allocation`` (as lazrs does)."""
    match path.read_text():
        case "ok":
            return
        case "refuse":
            raise FormatError(path, "not what this reader reads")
        case "refuse anonymously":
            raise FormatError("somewhere", "not what this reader reads")
        case "raise":
            raise ValueError("a reader bug")
        case "hang":
            time.sleep(3600)
        case "allocate":
            np.ones(1 << 30, dtype=np.uint8)  # 1 GB, over the harness's 256 MB
        case "abort":
            os.abort()
        case "abort after a failed allocation":
            sys.stderr.write("memory allocation of 85899338400 bytes failed\n")
            sys.stderr.flush()
            os.abort()
