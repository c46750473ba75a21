"""Engine settings by name: ``[engine]`` in session.toml, a job's parameters and ``slam6d run``'s flags
all become one :class:`~slam6d.pipeline.PipelineConfig` here.

Names are the config dataclasses' field names (``voxel_size``, ``relaxation``, ``loop.max_distance``
given as a table ``loop = {...}``); ``icp.*`` may also be written flat as ``icp_<name>``. Unknown
names are refused with the list of known ones: a typo must not silently run with defaults.
Keys starting with ``display_`` belong to the workbench's 3D view and are skipped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from slam6d.errors import Slam6dError
from slam6d.pipeline import PipelineConfig

__all__ = ["SettingsError", "pipeline_config"]


class SettingsError(Slam6dError):
    """An engine setting is unknown or has a value its config field cannot take."""


def _build(cls: type, values: Mapping[str, Any], what: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise SettingsError(f"unknown {what} parameter(s): {', '.join(unknown)}; known: {', '.join(sorted(fields))}")
    kwargs = {}
    defaults = cls()
    for name, value in values.items():
        default = getattr(defaults, name)
        if dataclasses.is_dataclass(default) and isinstance(value, Mapping):
            value = _build(type(default), value, f"{what}.{name}")
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise SettingsError(f"{what}: {exc}") from None


def pipeline_config(*sources: Mapping[str, Any] | None) -> PipelineConfig:
    """A PipelineConfig from settings by name; later sources override earlier ones (session.toml, then a run's own)."""
    values: dict[str, Any] = {}
    for source in sources:
        for key, value in (source or {}).items():
            if key.startswith("display_"):  # settings of the 3D view, not of the engine
                continue
            if key.startswith("icp_"):
                values.setdefault("icp", {})[key[4:]] = value
            elif key == "icp" and isinstance(value, Mapping):
                values.setdefault("icp", {}).update(value)
            else:
                values[key] = value
    config: PipelineConfig = _build(PipelineConfig, values, "pipeline")
    return config
