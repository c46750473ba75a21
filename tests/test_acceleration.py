"""Anderson's mixing and the pose chart it works in (slam6d.acceleration)."""

from __future__ import annotations

import numpy as np
import pytest

from slam6d.acceleration import AndersonMixer, PoseChart
from slam6d.geometry import pose_from_xyzrpy


def _slow_linear_map() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """y -> A y + b with one slow mode (contraction 0.5, as LUM's rounds on a long loop's scale)
    and fast ones (0.05), in a rotated basis: the map, its offset and its fixed point."""
    rng = np.random.default_rng(2)
    basis, _ = np.linalg.qr(rng.normal(size=(12, 12)))
    contraction = np.diag([0.5] + [0.05] * 11)
    a = basis @ contraction @ basis.T
    b = rng.normal(size=12)
    return a, b, np.linalg.solve(np.eye(12) - a, b)


def _iterations_to(tolerance: float, mixer: AndersonMixer | None) -> int:
    a, b, fixed = _slow_linear_map()
    y = np.zeros(12)
    for k in range(1, 60):
        image = a @ y + b
        y = mixer.mix(y, image) if mixer is not None else image
        if np.linalg.norm(y - fixed) < tolerance:
            return k
    return 60


def test_mixing_finds_the_fixed_point_of_a_slowly_contracting_map_in_a_few_steps() -> None:
    """The plain iteration needs ~20 steps to 1e-6 on the slow mode; Anderson's mixing of one past
    step finds a linear map's slow mode from two steps and is there in a few."""
    plain = _iterations_to(1e-6, None)
    mixed = _iterations_to(1e-6, AndersonMixer(depth=2))
    assert plain >= 18
    assert mixed <= 8, (plain, mixed)


def test_mixing_without_history_or_after_a_reset_is_the_plain_iteration() -> None:
    mixer = AndersonMixer(depth=1)
    y, image = np.zeros(6), np.arange(6.0)
    assert np.array_equal(mixer.mix(y, image), image)
    mixer.mix(image, image * 0.5)
    mixer.reset()
    assert np.array_equal(mixer.mix(y, image), image)


def test_a_stalled_history_falls_back_to_the_plain_step() -> None:
    """Two steps whose residuals barely differ would ask for an enormous extrapolation: refused."""
    mixer = AndersonMixer(depth=1, max_coefficient=10.0)
    mixer.mix(np.zeros(3), np.ones(3))
    image = np.ones(3) * 2.0
    assert np.array_equal(mixer.mix(np.ones(3) * (1.0 - 1e-9), image), image)


def test_depth_must_be_positive() -> None:
    with pytest.raises(ValueError, match="depth"):
        AndersonMixer(depth=0)


def test_pose_chart_round_trips_and_is_zero_at_its_origins() -> None:
    origins = [pose_from_xyzrpy(1.0, -2.0, 0.5, 0.1, -0.2, 2.5), pose_from_xyzrpy(-3.0, 0.0, 1.0, 0.0, 0.3, -1.0)]
    chart = PoseChart(origins)
    assert np.allclose(chart.vectors(origins), 0.0, atol=1e-12)
    moved = [o @ pose_from_xyzrpy(0.2, 0.1, -0.05, 0.02, 0.03, -0.04) for o in origins]
    vectors = chart.vectors(moved)
    assert np.allclose(chart.poses(vectors), moved, atol=1e-12)
    # the translation part is the offset in the origin's own frame
    assert np.allclose(vectors[:, :3], [[0.2, 0.1, -0.05]] * 2, atol=1e-12)
    # a subset of the origins
    which = np.array([1])
    assert np.allclose(chart.poses(chart.vectors(moved[1:], which), which), moved[1:], atol=1e-12)
