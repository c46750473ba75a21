"""Typed request values shared by every route: strict bodies, bounded indices, rigid poses, unit quaternions.

Request bodies are strict: a JSON ``false`` is not the number 0, ``"3"`` is not 3, and ``NaN`` or
``Infinity`` (which Python's JSON parser accepts) are not numbers at all. Indices and revisions are
bounded so that a number past 64 bits is a 422, not an overflow inside SQLite; poses and
quaternions are checked by the engine's own functions, so the API refuses exactly what the journal
would, with a message naming the field, before anything is stored.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from slam6d.geometry import MAX_COORDINATE_M, check_point, check_quaternion, check_rigid

# Far above any count of scans, keyframes or revisions, far below SQLite's 64-bit integers.
MAX_INDEX = 2**31 - 1


class RequestBody(BaseModel):
    """Base of every JSON request body: strict types, finite numbers."""

    model_config = ConfigDict(strict=True, allow_inf_nan=False)


def _rigid(value: list[list[float]]) -> list[list[float]]:
    return check_rigid(value, "pose").tolist()


def _quaternion(value: list[float]) -> list[float]:
    return check_quaternion(value, "orientation_wxyz").tolist()


def _point(value: list[float]) -> list[float]:
    return check_point(value, "position").tolist()


Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]
RigidPose = Annotated[
    list[Annotated[list[float], Field(min_length=4, max_length=4)]],
    Field(
        min_length=4, max_length=4, description="4x4 rigid transform: orthonormal rotation, det +1, last row 0 0 0 1"
    ),
    AfterValidator(_rigid),
]
Quaternion = Annotated[
    list[float],
    Field(min_length=4, max_length=4, description="w, x, y, z (normalised here)"),
    AfterValidator(_quaternion),
]
Point = Annotated[list[Coordinate], Field(min_length=3, max_length=3), AfterValidator(_point)]
Index = Annotated[int, Field(ge=0, le=MAX_INDEX)]
IndexPath = Annotated[int, Path(ge=0, le=MAX_INDEX)]
RevisionQuery = Annotated[int | None, Query(ge=0, le=MAX_INDEX, description="a revision number (default: current)")]
