"""Traces: what each engine step did, in a form the workbench can show without recomputing.

Every step (ICP, octree search, loop detection, relaxation) returns a dataclass trace; this
module turns any of them into plain JSON (numpy arrays become nested lists, 4x4 poses stay
row-major) and back to dicts, so traces can be saved with ``--trace`` and replayed.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def to_jsonable(value: Any) -> Any:
    """Recursively convert dataclasses, numpy arrays and scalars into JSON-ready values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value) if f.repr}
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def write_trace(path: Path, trace: Any) -> None:
    """Write a trace as indented JSON (atomically, so a crash never leaves half a file)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(trace), indent=1))
    tmp.replace(path)


def read_trace(path: Path) -> Any:
    return json.loads(Path(path).read_text())
