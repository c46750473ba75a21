"""open3d without its plotly viewer: the geometry and registration the engine uses, not dash.

``import open3d`` imports ``open3d.visualization``, which imports ``draw_plotly`` - a notebook
viewer built on plotly and dash - whatever the caller wants. Loading dash, plotly and the IPython
parts they pull in is about half of importing open3d: 0.6 of 1.2 s of CPU (``python -X importtime
-c "import open3d"``), paid by every ``slam6d run`` whose feature guess runs (the hand-held indoor
walks without odometry, where the octree search finds no fit) and by every ``slam6d simulate``
(the ray caster), neither of which draws anything.

:func:`defer_plotly_viewer` puts a stand-in for ``open3d.visualization.draw_plotly`` in
``sys.modules`` before open3d is first imported, so open3d's own ``from .draw_plotly import ...``
finds it and loads nothing. The stand-in defers rather than removes: calling any of its functions
(or reading any other attribute) loads the real module then, puts its functions back where open3d
had them, and answers with the real one, so code that does use open3d's plotly viewer in the same
process still works, at the price it always had.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any

VIEWER = "open3d.visualization.draw_plotly"
"""The module open3d imports for its plotly viewer (``open3d/visualization/__init__.py``, open3d 0.20)."""

VIEWER_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")
"""What ``open3d.visualization`` imports from it by name. Should an open3d import another name, the
stand-in's ``__getattr__`` loads the real module for it: the saving is lost, nothing breaks."""


def _real_viewer() -> ModuleType:
    """The real viewer module, loaded now in place of the stand-in, its functions back on
    ``open3d.visualization`` (importing a submodule sets the package's attribute of the same name to
    the module, which would hide the ``draw_plotly`` function open3d exports there)."""
    stand_in = sys.modules.get(VIEWER)
    if stand_in is not None and getattr(stand_in, "__slam6d_stand_in__", False):
        del sys.modules[VIEWER]
    real = importlib.import_module(VIEWER)
    visualization = sys.modules.get("open3d.visualization")
    if visualization is not None:
        for name in VIEWER_FUNCTIONS:
            if hasattr(real, name):
                setattr(visualization, name, getattr(real, name))
    return real


def _forward(name: str) -> Callable[..., Any]:
    def forwarded(*args: Any, **kwargs: Any) -> Any:
        return getattr(_real_viewer(), name)(*args, **kwargs)

    forwarded.__name__ = forwarded.__qualname__ = name
    forwarded.__doc__ = f"open3d's ``{name}``, loaded with plotly and dash on the first call."
    return forwarded


def _module_getattr(name: str) -> Any:
    if name.startswith("__"):  # the import system asks for __path__ and the like: not a use of the viewer
        raise AttributeError(f"module {VIEWER!r} has no attribute {name!r}")
    return getattr(_real_viewer(), name)


def defer_plotly_viewer() -> bool:
    """Put the stand-in in place if open3d is not imported yet; whether it did. Call it right before
    ``import open3d``; an open3d loaded already (with its viewer) is left as it is."""
    if "open3d" in sys.modules or VIEWER in sys.modules:
        return False
    stand_in = ModuleType(VIEWER, "Stand-in for open3d's plotly viewer, loaded on first use (slam6d.open3d_viewer).")
    stand_in.__slam6d_stand_in__ = True  # type: ignore[attr-defined]
    for name in VIEWER_FUNCTIONS:
        setattr(stand_in, name, _forward(name))
    stand_in.__getattr__ = _module_getattr  # type: ignore[method-assign]  # PEP 562: any other name loads the real one
    sys.modules[VIEWER] = stand_in
    return True
