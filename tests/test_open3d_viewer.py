"""open3d loads without its plotly viewer where the engine uses it (the feature guess, the
simulator's ray caster), and the viewer still works for code that calls it.

Each check runs in a fresh process: what a process has imported is the behaviour under test."""

from __future__ import annotations

from tests.cli_process import python_result

_FEATURE_GUESS_THEN_VIEWER = """
import json, sys
import numpy as np
from slam6d.features import feature_guess

rng = np.random.default_rng(3)
# three walls and a floor of a 6 x 4 x 3 m room, and a box in it: enough shape for FPFH
faces = [
    np.c_[rng.uniform(0, 6, 3000), np.zeros(3000), rng.uniform(0, 3, 3000)],
    np.c_[np.zeros(3000), rng.uniform(0, 4, 3000), rng.uniform(0, 3, 3000)],
    np.c_[rng.uniform(0, 6, 3000), rng.uniform(0, 4, 3000), np.zeros(3000)],
    np.c_[rng.uniform(2, 3, 1500), rng.uniform(1, 2, 1500), np.full(1500, 1.0)],
    np.c_[np.full(1500, 2.0), rng.uniform(1, 2, 1500), rng.uniform(0, 1, 1500)],
]
model = np.vstack(faces)
guess = feature_guess(model, model + [0.3, 0.0, 0.0])
after_guess = {name: name in sys.modules for name in ("open3d", "dash", "plotly")}

import open3d
cloud = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(model[:100]))
figure = open3d.visualization.get_plotly_fig([cloud])
print(json.dumps({
    "after_guess": after_guess,
    "moved_x": float(guess.transform[0, 3]),
    "figure": type(figure).__module__.split(".")[0],
    "after_viewer": {name: name in sys.modules for name in ("dash", "plotly")},
    "draw_plotly_is_function": callable(open3d.visualization.draw_plotly)
    and not isinstance(open3d.visualization.draw_plotly, type(sys)),
}))
"""


def test_the_feature_guess_loads_open3d_without_dash_and_the_viewer_loads_on_first_use() -> None:
    result = python_result(_FEATURE_GUESS_THEN_VIEWER)
    assert result["after_guess"] == {"open3d": True, "dash": False, "plotly": False}
    # the guess itself worked: the data, the model moved by +0.3 m in x, goes back by about that
    assert abs(float(result["moved_x"]) + 0.3) < 0.15  # type: ignore[arg-type]
    # open3d's own viewer, called afterwards in the same process, loads the real thing and answers
    assert result["figure"] == "plotly"
    assert result["after_viewer"] == {"dash": True, "plotly": True}
    assert result["draw_plotly_is_function"] is True


def test_simulating_loads_no_dash() -> None:
    code = (
        "import json, sys, tempfile; from pathlib import Path\n"
        "from slam6d.simulate import SimulationConfig, simulate_session\n"
        "with tempfile.TemporaryDirectory() as tmp:\n"
        "    simulate_session(Path(tmp) / 's', SimulationConfig(seed=1, scans=2, sensor='vlp16', world='indoor'))\n"
        "print(json.dumps({m: m in sys.modules for m in ('open3d', 'dash', 'plotly')}))"
    )
    assert python_result(code) == {"open3d": True, "dash": False, "plotly": False}


def test_an_open3d_loaded_already_is_left_alone() -> None:
    code = (
        "import json, sys, open3d; from slam6d.open3d_viewer import VIEWER, defer_plotly_viewer\n"
        "before = sys.modules[VIEWER]\n"
        "print(json.dumps({'deferred': defer_plotly_viewer(), 'same': sys.modules[VIEWER] is before,"
        " 'dash': 'dash' in sys.modules}))"
    )
    assert python_result(code) == {"deferred": False, "same": True, "dash": True}
