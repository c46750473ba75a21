"""The workbench's REST server without 3D views, for the SIGKILL harness: ``python -m tests.fault.serve DIR PORT``."""

from __future__ import annotations

import sys
from pathlib import Path

import uvicorn

from app.server import create_app

if __name__ == "__main__":
    uvicorn.run(
        create_app(Path(sys.argv[1]), viewers=False), host="127.0.0.1", port=int(sys.argv[2]), log_level="error"
    )
