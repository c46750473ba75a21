"""Pose-graph least squares, simultaneous matching and LUM relaxation on small synthetic problems."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from slam6d.engine_settings import SettingsError, pipeline_config
from slam6d.errors import RelaxationError
from slam6d.geometry import (
    invert,
    make_pose,
    pose_difference,
    pose_from_xyzrpy,
    so3_exp,
    so3_log,
    transform_points,
)
from slam6d.icp import ICPConfig
from slam6d.lum import lum_relaxation
from slam6d.metrics import absolute_trajectory_error
from slam6d.posegraph import (
    PoseEdge,
    optimize_pose_graph,
    point_pair_information,
)
from slam6d.relax import (
    RelaxationConfig,
    ScanModels,
    carry_forward,
    gathered,
    neighbour_graph,
    pair_residual,
    spread_evenly,
)
from slam6d.simultaneous import simultaneous_matching
from tests.simulated_loop import simulated_loop


def _ring(count: int = 12, radius: float = 10.0) -> list[np.ndarray]:
    angles = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    return [
        pose_from_xyzrpy(radius * np.cos(a), radius * np.sin(a), 0.1 * np.sin(3 * a), 0.02, -0.01, a + np.pi / 2)
        for a in angles
    ]


def _noisy(pose: np.ndarray, rng: np.random.Generator, t: float, r: float) -> np.ndarray:
    return pose @ make_pose(so3_exp(rng.normal(0, r, 3)), rng.normal(0, t, 3))


def test_so3_log_inverts_exp_including_near_pi() -> None:
    rng = np.random.default_rng(0)
    vectors = rng.normal(size=(200, 3))
    vectors *= (rng.uniform(0, np.pi - 1e-4, 200) / np.linalg.norm(vectors, axis=1))[:, None]
    vectors[0] = [np.pi - 1e-7, 0.0, 0.0]
    vectors[1] = [0.0, 0.0, 1e-10]
    back = so3_log(so3_exp(vectors))
    np.testing.assert_allclose(so3_exp(back), so3_exp(vectors), atol=1e-7)  # near pi the axis is only ~sqrt(eps) exact
    np.testing.assert_allclose(back[2:], vectors[2:], atol=1e-6)


def test_consistent_loop_graph_recovers_the_truth_from_drifted_start() -> None:
    truth = _ring()
    edges = [PoseEdge(k, (k + 1) % 12, invert(truth[k]) @ truth[(k + 1) % 12]) for k in range(12)]
    edges.append(PoseEdge(0, 6, invert(truth[0]) @ truth[6]))
    rng = np.random.default_rng(1)
    start = [truth[0]] + [_noisy(p, rng, 0.5, 0.1) for p in truth[1:]]
    result = optimize_pose_graph(start, edges, fixed=[0])
    assert result.converged
    assert result.residual_after < 1e-12 < result.residual_before
    for got, want in zip(result.poses, truth, strict=True):
        dt, dr = pose_difference(got, want)
        assert dt < 1e-6 and dr < 1e-6


def test_loop_edge_spreads_odometry_drift_and_matches_weighted_optimum() -> None:
    """Chained noisy odometry plus one accurate loop edge: the error at the loop end shrinks a lot."""
    truth = _ring(30, 20.0)
    rng = np.random.default_rng(2)
    odo_info = np.diag([1 / 0.05**2] * 3 + [1 / 0.01**2] * 3)
    edges = [PoseEdge(k, k + 1, _noisy(invert(truth[k]) @ truth[k + 1], rng, 0.05, 0.01), odo_info) for k in range(29)]
    loop = PoseEdge(0, 29, invert(truth[0]) @ truth[29], np.eye(6) * 1e6)
    chained = [truth[0]]
    for edge in edges:
        chained.append(chained[-1] @ edge.measurement)
    result = optimize_pose_graph(chained, [*edges, loop], fixed=[0])
    before = absolute_trajectory_error(chained, truth, align=False).rmse
    after = absolute_trajectory_error(result.poses, truth, align=False).rmse
    assert pose_difference(result.poses[29], truth[29])[0] < 0.01
    assert after < 0.5 * before
    # at the optimum the gradient vanishes: a second solve from the result does not move
    again = optimize_pose_graph(result.poses, [*edges, loop], fixed=[0])
    assert again.residual_after == pytest.approx(result.residual_after, rel=1e-6)


def test_loop_edge_takes_a_pitch_drift_out_of_the_middle_of_the_path() -> None:
    """Odometry whose every step is tilted by the same 0.1° of pitch climbs 3.9 m over 130 m of a
    flat arc (1.1 m half-way); one accurate edge between its ends, solved with the odometry, turns
    each step's tilt back, so the correction reaches the middle: no pose stays 10 cm off in height."""
    angles = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)[:42]
    truth = [pose_from_xyzrpy(100 * np.cos(a), 100 * np.sin(a), 0.0, 0.0, 0.0, a + np.pi / 2) for a in angles]
    tilt = make_pose(so3_exp(np.array([0.0, np.radians(0.1), 0.0])), np.zeros(3))
    steps = [invert(truth[k]) @ truth[k + 1] @ tilt for k in range(41)]
    chained = [truth[0]]
    for step in steps:
        chained.append(chained[-1] @ step)
    height = [abs(c[2, 3] - t[2, 3]) for c, t in zip(chained, truth, strict=True)]
    assert max(height) > 3.5 and height[21] > 1.0
    edges = [PoseEdge(k, k + 1, steps[k]) for k in range(41)]
    loop = PoseEdge(0, 41, invert(truth[0]) @ truth[41], np.eye(6) * 100.0)
    result = optimize_pose_graph(chained, [*edges, loop], fixed=[0])
    height = [abs(r[2, 3] - t[2, 3]) for r, t in zip(result.poses, truth, strict=True)]
    assert max(height) < 0.1, max(height)


def test_disconnected_graph_fails_naming_the_loose_scans() -> None:
    truth = _ring(6)
    edges = [PoseEdge(0, 1, invert(truth[0]) @ truth[1]), PoseEdge(3, 4, invert(truth[3]) @ truth[4])]
    with pytest.raises(RelaxationError, match=r"disconnected: 4 scan\(s\) \(2, 3, 4, 5\)"):
        optimize_pose_graph(truth, edges, fixed=[0])
    with pytest.raises(RelaxationError, match="no edges"):
        optimize_pose_graph(truth, [], fixed=[0])
    with pytest.raises(RelaxationError, match="missing scan"):
        optimize_pose_graph(truth, [PoseEdge(0, 9, np.eye(4))], fixed=[0])


def test_degenerate_information_is_reported_as_solver_failure() -> None:
    truth = _ring(3)
    flat = np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 1.0])  # nothing constrains z
    edges = [PoseEdge(0, 1, invert(truth[0]) @ truth[1], flat), PoseEdge(1, 2, invert(truth[1]) @ truth[2], flat)]
    with pytest.raises(RelaxationError, match=r"singular|non-finite"):
        optimize_pose_graph(truth, edges, fixed=[0])


def test_point_pair_information_sees_the_free_direction_of_a_plane() -> None:
    rng = np.random.default_rng(3)
    plane = np.column_stack([rng.uniform(-5, 5, 500), rng.uniform(-5, 5, 500), np.zeros(500)])
    info = point_pair_information(plane, np.eye(4), 0.01**2)
    assert np.allclose(info, info.T)
    assert np.linalg.eigvalsh(info).min() > -1e-6
    # point-to-point pairs constrain all translations equally, rotation about z less than tilts
    assert info[0, 0] == pytest.approx(500 / 0.01**2)
    assert info[5, 5] > 0 and info[3, 3] < 2 * info[5, 5]


def test_carry_forward_keeps_unrelaxed_scans_attached() -> None:
    before = _ring(5)
    shift = make_pose(so3_exp(np.array([0, 0, 0.1])), [1.0, 0, 0])
    after = [p.copy() for p in before]
    after[2] = shift @ before[2]
    out = carry_forward(before, after, relaxed=[0, 1, 2])
    for k in (3, 4):
        np.testing.assert_allclose(out[k], shift @ before[k], atol=1e-12)
    np.testing.assert_allclose(out[1], before[1])


@pytest.fixture(scope="module")
def loop_scans():  # type: ignore[no-untyped-def]
    sim = simulated_loop(scans=10, points=30000, seed=4, loop_length=16.0, loop_width=10.0)
    config = ICPConfig(max_distance=0.3, max_iterations=30)
    from slam6d.octree import reduce_points

    points = [s.points[reduce_points(s.points, 0.1)] for s in sim.sequence]
    return sim, ScanModels(points, config)


def _perturbed(truth: list[np.ndarray], seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [truth[0]] + [_noisy(p, rng, 0.05, np.radians(0.5)) for p in truth[1:]]


@pytest.mark.parametrize(("method", "tolerance"), [("simultaneous", 0.025), ("lum", 0.012)])
def test_relaxation_pulls_perturbed_scans_back_to_the_truth(loop_scans, method: str, tolerance: float) -> None:  # type: ignore[no-untyped-def]
    sim, models = loop_scans
    start = _perturbed(sim.truth, 5)
    relax = simultaneous_matching if method == "simultaneous" else lum_relaxation
    reported: list[float] = []
    result = relax(
        models, start, fixed=[0], config=RelaxationConfig(), progress=lambda _n, residual, _m: reported.append(residual)
    )
    before = absolute_trajectory_error(start, sim.truth, align=False).rmse
    after = absolute_trajectory_error(result.poses, sim.truth, align=False).rmse
    assert before > 0.04
    assert after < tolerance, (before, after)
    # the residuals are point-to-plane distances in metres: at the end as small as at the true poses
    at_truth = pair_residual(models, sim.truth, result.neighbours)
    assert result.residual_before > 1.5 * at_truth
    assert result.residual_after < 1.2 * at_truth, (result.residual_after, at_truth)
    assert reported and all(0 < r < models.config.max_distance for r in reported)
    np.testing.assert_allclose(result.poses[0], sim.truth[0])  # the first scan is fixed


def test_neighbours_need_overlap(loop_scans) -> None:  # type: ignore[no-untyped-def]
    sim, models = loop_scans
    pairs = neighbour_graph(models, sim.truth, min_pairs=250).pairs
    linked = {(p.i, p.j) for p in pairs}
    assert all((k, k + 1) in linked for k in range(9))
    moved = [p.copy() for p in sim.truth]
    moved[5] = make_pose(np.eye(3), [500.0, 0, 0]) @ moved[5]
    assert not any(5 in (p.i, p.j) for p in neighbour_graph(models, moved, min_pairs=250).pairs)
    with pytest.raises(RelaxationError, match=r"disconnected.*5"):
        lum_relaxation(models, moved, fixed=[0])


@pytest.mark.parametrize("exponent", [1.0, 0.0])
def test_lum_budget_grows_with_the_graph_and_weights_pairs_by_overlap(loop_scans, exponent: float) -> None:  # type: ignore[no-untyped-def]
    """Points per round follow the number of pairs; a pair's total pull follows overlap**exponent."""
    from slam6d.lum import _edge_budget

    sim, models = loop_scans
    pairs = neighbour_graph(models, sim.truth, min_pairs=250).pairs
    config = _as_large_session(pair_points=300, overlap_exponent=exponent, min_edge_points=1, edge_points=10**6)
    budget = _edge_budget(models, pairs, config)
    assert sum(c for c, _ in budget.values()) == pytest.approx(300 * len(pairs), rel=0.02)
    overlap = np.array([p.pairs / len(models.points[p.j]) for p in pairs])
    pull = np.array([c * w for c, w in (budget[(p.i, p.j)] for p in pairs)])
    np.testing.assert_allclose(pull / pull.mean(), overlap**exponent / np.mean(overlap**exponent), rtol=0.05)
    halved = _edge_budget(models, pairs[::2], config)
    assert sum(c for c, _ in halved.values()) == pytest.approx(300 * len(pairs[::2]), rel=0.02)


def test_lum_pair_blocks_match_the_numpy_jacobians() -> None:
    """The compiled per-pair accumulation equals J^T W J and J^T W r built from explicit Jacobians."""
    from slam6d.lum import _pair_blocks
    from slam6d.relax import place

    rng = np.random.default_rng(3)
    n, pairs, scale = 400, 3, 0.05
    relative = np.stack([_noisy(np.eye(4), rng, 1.0, 0.3) for _ in range(pairs)])
    source = np.sort(rng.integers(0, pairs, n))
    p = rng.normal(0, 5, (n, 3))
    q = place(p, source, relative)
    np.testing.assert_allclose(q, np.einsum("nij,nj->ni", relative[source, :3, :3], p) + relative[source, :3, 3])
    m = q + rng.normal(0, 0.05, (n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    blocks, gradients, sums = _pair_blocks(q, p, np.arange(n), m, normals, relative, source, pairs, scale)
    r = np.einsum("ij,ij->i", q - m, normals)
    n_j = np.einsum("nk,nkl->nl", normals, relative[source, :3, :3])
    jac = np.hstack([-normals, -np.cross(q, normals), n_j, np.cross(p, n_j)])
    w = 1 / (1 + (r / scale) ** 2)
    for s in range(pairs):
        at = source == s
        np.testing.assert_allclose(blocks[s], (jac[at] * w[at, None]).T @ jac[at], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(gradients[s], (jac[at] * (w * r)[at, None]).sum(axis=0), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(sums[s], [np.sum(r[at] ** 2), np.sum(w[at] * r[at] ** 2), at.sum()], rtol=1e-10)


def test_lum_reports_the_residual_at_the_final_poses_and_stops_once_settled(loop_scans) -> None:  # type: ignore[no-untyped-def]
    """Before/after come from the rounds' own queries; after must still describe the returned poses."""
    from slam6d.lum import _batches, _edge_budget, _round_residual

    sim, models = loop_scans
    config = RelaxationConfig()
    result = lum_relaxation(models, _perturbed(sim.truth, 5), fixed=[0], config=config)
    batches = _batches(models, result.neighbours, _edge_budget(models, result.neighbours, config))
    assert result.residual_after == pytest.approx(_round_residual(models, result.poses, batches), rel=0.02)
    assert result.residual_after < result.residual_before
    # from the truth nothing moves: the thin sample settles by its second round at the final robust
    # scale, and the full sample's two rounds end it
    settled = lum_relaxation(models, sim.truth, fixed=[0], config=config)
    assert settled.iterations <= 5
    assert absolute_trajectory_error(settled.poses, sim.truth, align=False).rmse < 0.005


def _as_large_session(**fields: object) -> RelaxationConfig:
    """LUM's settings with the rounds' sample drawn per pair as on a large session: the 10-scan
    fixture would otherwise sample at ``min_round_points``, the few-scan floor, and the per-pair
    budget and the thin rounds these tests are about would not show."""
    return RelaxationConfig(min_round_points=0, **fields)  # type: ignore[arg-type]


def _noisy_start(truth: list[np.ndarray], offset: float, angle: float) -> list[np.ndarray]:
    """The truth with every scan but the first moved by ``offset`` metres and ``angle`` radians
    (seeded, so a thin-rounds test and its full-sample twin start alike)."""
    rng = np.random.default_rng(5)
    return [truth[0]] + [_noisy(p, rng, offset, angle) for p in truth[1:]]


def _queried_points_per_round(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """A list that receives, per LUM round, how many data points the round queries: what tells the
    thin sample's rounds from the full sample's."""
    import slam6d.lum as lum

    queried: list[int] = []
    joint_step = lum._joint_step

    def counted(models, current, batches, *args, **kwargs):  # type: ignore[no-untyped-def]
        queried.append(sum(len(b.points) for b in batches))
        return joint_step(models, current, batches, *args, **kwargs)

    monkeypatch.setattr(lum, "_joint_step", counted)
    return queried


@pytest.mark.parametrize(("offset", "angle"), [(0.02, 0.2), (0.08, 0.8)])
def test_lum_takes_a_far_start_in_thin_rounds_and_settles_in_two_full_ones(
    loop_scans,  # type: ignore[no-untyped-def]
    monkeypatch,  # type: ignore[no-untyped-def]
    offset: float,
    angle: float,
) -> None:
    """Each round goes only part of the way, so the rounds a relaxation needs grow with how far off it
    starts (the dense loop: 4 at 100 scans, 8 at 400, docs/scale.md). Those rounds run on the thin
    sample (``coarse_fraction``): a start 4x farther off costs more thin rounds, yet the full sample
    is queried in exactly two rounds either way, and the result is as close to the truth as with
    every round on the full sample (whose rounds do grow with the start's error)."""
    sim, models = loop_scans
    start = _noisy_start(sim.truth, offset, np.radians(angle))
    queried = _queried_points_per_round(monkeypatch)
    thin = lum_relaxation(models, start, fixed=[0], config=_as_large_session())
    full_size = max(queried)
    thin_rounds = [n for n in queried if n < full_size]
    assert len(queried) == thin.iterations and queried == thin_rounds + [full_size] * 2, queried
    assert max(thin_rounds) < 0.35 * full_size
    queried.clear()
    full = lum_relaxation(models, start, fixed=[0], config=_as_large_session(coarse_fraction=1.0))
    assert queried == [full_size] * full.iterations
    assert full.iterations >= (5 if offset > 0.05 else 4)  # the rounds that the thin sample takes over
    thin_error = absolute_trajectory_error(thin.poses, sim.truth, align=False).rmse
    full_error = absolute_trajectory_error(full.poses, sim.truth, align=False).rmse
    assert absolute_trajectory_error(start, sim.truth, align=False).rmse > 5 * full_error
    assert thin_error < 1.2 * full_error + 0.001, (thin_error, full_error)


def test_lum_mixing_past_rounds_takes_fewer_rounds_to_the_same_poses(loop_scans) -> None:  # type: ignore[no-untyped-def]
    """Anderson's mixing of the rounds (``acceleration_depth``, slam6d.acceleration) reaches what the
    plain rounds reach, in fewer rounds, from a start far enough off that the plain rounds take
    more than the fewest (every round on the full sample, so that the rounds counted are the
    mixing's alone; on the dense loop at 400 scans it took LUM from 8 rounds to 6, docs/scale.md)."""
    sim, models = loop_scans
    start = _noisy_start(sim.truth, 0.08, np.radians(0.8))
    plain = lum_relaxation(
        models, start, fixed=[0], config=_as_large_session(coarse_fraction=1.0, acceleration_depth=0)
    )
    mixed = lum_relaxation(
        models, start, fixed=[0], config=_as_large_session(coarse_fraction=1.0, acceleration_depth=1)
    )
    assert mixed.iterations < plain.iterations
    plain_error = absolute_trajectory_error(plain.poses, sim.truth, align=False).rmse
    mixed_error = absolute_trajectory_error(mixed.poses, sim.truth, align=False).rmse
    assert mixed_error < 1.1 * plain_error + 0.0005, (mixed_error, plain_error)
    assert _apart(models, plain.poses, mixed.poses) < 0.002


def test_lum_refuses_mixed_poses_that_fit_worse_and_goes_back_to_the_plain_round(loop_scans) -> None:  # type: ignore[no-untyped-def]
    """The mixing's safeguard: when the round at the mixed poses finds a higher robust cost than the
    round they were mixed from, the scans go back to that round's plain result, and the history
    restarts (the next round is a plain one)."""
    from slam6d.lum import _Accelerator, _Round

    sim, models = loop_scans
    start = _noisy_start(sim.truth, 0.02, np.radians(0.2))
    accelerator = _Accelerator(models, start, depth=1)
    nudge = make_pose(np.eye(3), [0.01, 0.0, 0.0])
    first = {k: start[k] @ nudge for k in range(1, len(start))}
    assert accelerator.mixed(start, _Round(first, 1.0, 1.0, 0.01), (1, 0.05)) is first  # no history: plain
    current = [start[0]] + [first[k] for k in range(1, len(start))]
    second = {k: current[k] @ nudge @ nudge for k in range(1, len(start))}
    mixed = accelerator.mixed(current, _Round(second, 0.8, 0.8, 0.01), (1, 0.05))
    assert all(np.abs(mixed[k][:3, 3] - second[k][:3, 3]).max() > 1e-3 for k in mixed)  # extrapolated
    placed = [start[0]] + [mixed[k] for k in range(1, len(start))]
    kept = list(placed)
    assert not accelerator.rejects(0.7, kept)  # a lower cost there: the mixed poses stay
    assert all(kept[k] is placed[k] for k in range(len(placed)))
    # the same two rounds again, and this time the mixed poses' round finds a higher cost: refused
    accelerator = _Accelerator(models, start, depth=1)
    accelerator.mixed(start, _Round(first, 1.0, 1.0, 0.01), (1, 0.05))
    accelerator.mixed(current, _Round(second, 0.8, 0.8, 0.01), (1, 0.05))
    assert accelerator.rejects(0.9, placed)
    assert all(np.array_equal(placed[k], second[k]) for k in second)
    # history restarted: the next round is taken as it comes
    third = {k: second[k] @ nudge for k in second}
    assert accelerator.mixed(placed, _Round(third, 0.7, 0.7, 0.01), (1, 0.05)) is third


def test_lum_on_few_scans_samples_enough_points_not_to_leave_the_samples_noise_in_the_poses(loop_scans) -> None:  # type: ignore[no-untyped-def]
    """``pair_points`` per pair is few points when there are few pairs: on 10 scans ~11,000 per
    round, whose own optimum lies millimetres off the scans' (LUM run to convergence from the
    truth walked 4 mm away). ``min_round_points`` keeps a round's sample at least that large, so
    that relaxing the truth leaves it where it is."""
    sim, models = loop_scans
    converged = {"max_rounds": 20, "chi2_tolerance": 0.0, "tolerance": 0.0, "settle_fraction": 0.0}
    sampled = lum_relaxation(models, sim.truth, fixed=[0], config=RelaxationConfig(**converged))
    thin = lum_relaxation(models, sim.truth, fixed=[0], config=RelaxationConfig(min_round_points=0, **converged))
    assert absolute_trajectory_error(sampled.poses, sim.truth, align=False).rmse < 0.002
    assert absolute_trajectory_error(thin.poses, sim.truth, align=False).rmse > 0.003


def _apart(models: ScanModels, a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """How far two sets of poses put the scans apart: the mean over the scans of the largest
    displacement of a scan's points (200 of them, as LUM's rounds measure a scan's move)."""
    return float(
        np.mean(
            [
                np.linalg.norm(transform_points(x, pts) - transform_points(y, pts), axis=1).max()
                for k, (x, y) in enumerate(zip(a, b, strict=True))
                for pts in [models.thinned(k, 200)]
            ]
        )
    )


@pytest.mark.parametrize(("offset", "angle"), [(0.02, 0.2), (0.08, 0.8)])
def test_lum_thin_first_rounds_change_the_path_not_where_it_converges(
    loop_scans,  # type: ignore[no-untyped-def]
    monkeypatch,  # type: ignore[no-untyped-def]
    offset: float,
    angle: float,
) -> None:
    """The thin first rounds (``coarse_fraction``) lead the relaxation along another path, to the
    same poses: with the settle tests off, 16 rounds from either start end within 0.2 mm (mean over
    the scans of the largest displacement of a scan's points) of 16 rounds all on the full sample.
    With the default settle tests the two end 1.7-2.1 mm apart here, and BALM hall's RPE reads
    0.55 against 0.53 cm: not another optimum but two stops short of the same one, each where its
    settle tests first fired (docs/scale.md, "Where the rounds stop")."""
    sim, models = loop_scans
    start = _noisy_start(sim.truth, offset, np.radians(angle))
    unsettled = _as_large_session(tolerance=0.0, settle_fraction=0.0, chi2_tolerance=0.0, max_rounds=16)
    queried = _queried_points_per_round(monkeypatch)
    thin = lum_relaxation(models, start, fixed=[0], config=unsettled)
    assert sum(n < 0.35 * max(queried) for n in queried) >= 2  # the path did start on the thin sample
    full = lum_relaxation(models, start, fixed=[0], config=replace(unsettled, coarse_fraction=1.0))
    assert thin.iterations == full.iterations == 16
    assert _apart(models, thin.poses, full.poses) < 0.0002
    thin_error = absolute_trajectory_error(thin.poses, sim.truth, align=False).rmse
    full_error = absolute_trajectory_error(full.poses, sim.truth, align=False).rmse
    assert abs(thin_error - full_error) < 0.0001, (thin_error, full_error)


@pytest.mark.parametrize(("offset", "angle"), [(0.02, 0.2), (0.08, 0.8)])
def test_lum_settled_on_movement_ends_where_full_sample_rounds_end(
    loop_scans,  # type: ignore[no-untyped-def]
    monkeypatch,  # type: ignore[no-untyped-def]
    offset: float,
    angle: float,
) -> None:
    """``settle_on="movement"`` ends the rounds once they move the scans by less than ``tolerance``
    on average, so the thin first rounds only save time: the relaxation ends within 1 mm (mean over
    the scans of the largest displacement of a scan's points) of one with every round on the full
    sample, in fewer rounds on the full sample. Settled on the robust cost (the default) the two end
    2.1 and 1.7 mm apart here (docs/scale.md, "Where the rounds stop")."""
    sim, models = loop_scans
    start = _noisy_start(sim.truth, offset, np.radians(angle))
    queried = _queried_points_per_round(monkeypatch)
    config = RelaxationConfig(settle_on="movement")
    thin = lum_relaxation(models, start, fixed=[0], config=config)
    full_size = max(queried)
    thin_rounds = [n for n in queried if n < full_size]
    assert len(thin_rounds) >= 2 and queried == thin_rounds + [full_size] * (thin.iterations - len(thin_rounds))
    queried.clear()
    full = lum_relaxation(models, start, fixed=[0], config=replace(config, coarse_fraction=1.0))
    assert queried == [full_size] * full.iterations
    assert thin.iterations - len(thin_rounds) < full.iterations  # the full rounds the thin ones saved
    assert _apart(models, thin.poses, full.poses) < 0.001
    thin_error = absolute_trajectory_error(thin.poses, sim.truth, align=False).rmse
    full_error = absolute_trajectory_error(full.poses, sim.truth, align=False).rmse
    assert abs(thin_error - full_error) < 0.0002, (thin_error, full_error)


def test_lum_works_out_its_block_pattern_once_for_rounds_over_the_same_pairs(loop_scans, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The rounds' linear systems share one sparsity pattern: its ordering and symbolic factor are
    worked out once per relaxation, not once per round, and the poses are those of a fresh
    pattern every round (the factorisation itself is redone each round)."""
    import slam6d.lum as lum

    sim, models = loop_scans
    built: list[int] = []

    class Counted(lum.BlockSystem):
        def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
            built.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(lum, "BlockSystem", Counted)
    start = _perturbed(sim.truth, 5)
    result = lum_relaxation(models, start, fixed=[0], config=RelaxationConfig())
    assert result.iterations >= 3 and len(built) == 1
    original = lum._joint_step

    def fresh_pattern(*args):  # type: ignore[no-untyped-def]
        return original(*args[:-1])  # the same round without the patterns kept (the last argument)

    monkeypatch.setattr(lum, "_joint_step", fresh_pattern)
    again = lum_relaxation(models, start, fixed=[0], config=RelaxationConfig())
    assert len(built) == 1 + again.iterations
    for shared, fresh in zip(result.poses, again.poses, strict=True):
        np.testing.assert_allclose(shared, fresh, atol=1e-12)


def test_lum_pairs_against_a_shared_registration_model(loop_scans) -> None:  # type: ignore[no-untyped-def]
    """Rounds against models handed over (coarser plane sample, normals per cube) still find the truth."""
    from slam6d.model import ModelIndex

    sim, shared = loop_scans
    models = ScanModels(shared.points, shared.config)
    for k in range(len(models)):
        own = models.index(k)
        model = ModelIndex(own.points, normal_voxel_size=0.2, normal_cell=0.4, index=own.index)
        model.plane_normals()
        models.share_plane_model(k, model)
        assert models.plane_model(k) is model
    start = _perturbed(sim.truth, 5)
    result = lum_relaxation(models, start, fixed=[0])
    assert absolute_trajectory_error(result.poses, sim.truth, align=False).rmse < 0.012
    with pytest.raises(ValueError, match="scan 1"):
        models.share_plane_model(1, ModelIndex(models.points[2]))


def _dense_loop(scans: int, points: int = 4000):  # type: ignore[no-untyped-def]
    from slam6d.octree import reduce_points

    sim = simulated_loop(scans=scans, points=points, seed=4, loop_length=16.0, loop_width=10.0)
    reduced = [s.points[reduce_points(s.points, 0.1)] for s in sim.sequence]
    return sim, ScanModels(reduced, ICPConfig(max_distance=0.3, max_iterations=30))


def _components(count: int, pairs) -> int:  # type: ignore[no-untyped-def]
    parent = list(range(count))

    def root(k: int) -> int:
        while parent[k] != k:
            k = parent[k]
        return k

    for p in pairs:
        parent[root(p.i)] = root(p.j)
    return len({root(k) for k in range(count)})


@pytest.mark.parametrize("scans", [24, 72])
def test_bounded_neighbour_graph_stays_connected_within_its_bound(scans: int) -> None:
    """Whatever the density, each scan chooses at most ``per_scan`` neighbours (so the graph has at
    most per_scan x scans pairs) and the graph stays one piece, with the loop's closing pairs in it."""
    sim, models = _dense_loop(scans)
    per_scan = 6
    every = neighbour_graph(models, sim.truth, min_pairs=100).pairs
    bounded = neighbour_graph(models, sim.truth, min_pairs=100, per_scan=per_scan).pairs
    assert len(bounded) <= per_scan * scans
    assert all(p.pairs > 100 and p.i < p.j for p in bounded)
    assert _components(scans, bounded) == 1
    linked = {(p.i, p.j) for p in bounded}
    assert all((k, k + 1) in linked for k in range(scans - 1))
    # spread along the path: pairs across the loop's seam (first scans with the last ones) are kept
    assert any(p.j - p.i > scans // 2 for p in bounded)
    if scans == 72:  # dense: every overlapping pair is several times the bound
        assert len(every) > 2 * len(bounded)


@pytest.mark.parametrize("scans", [72, 144])
def test_bounded_graph_counts_overlap_with_about_per_scan_pairs_per_scan_whatever_the_density(scans: int) -> None:
    """The graph's cost is the pairs whose overlap it counts. On a loop scanned ever more densely the
    bounded graph counts about ``per_scan`` pairs per scan (each scan's tally of ``2 x per_scan``
    includes the pairs counted from the other side), while counting every overlapping pair costs
    per scan what the density is. Before the tally, each scan counted ``2 x per_scan`` candidates of
    its own, most not mutual: 9.5 and 10 pairs per scan here for ``per_scan`` 6."""
    sim, models = _dense_loop(scans)
    per_scan = 6
    bounded = neighbour_graph(models, sim.truth, min_pairs=100, per_scan=per_scan)
    every = neighbour_graph(models, sim.truth, min_pairs=100)
    assert bounded.counted <= 1.35 * per_scan * scans
    assert every.counted > 3 * bounded.counted  # 35 and 72 pairs per scan
    assert len(bounded.pairs) <= per_scan * scans and _components(scans, bounded.pairs) == 1


def test_bounded_graph_relaxes_a_dense_loop_as_well_as_the_full_graph() -> None:
    sim, models = _dense_loop(24, points=30000)
    start = _perturbed(sim.truth, 5)
    errors = {}
    for per_scan in (0, 8):
        config = RelaxationConfig(min_pairs=100, neighbours_per_scan=per_scan)
        result = lum_relaxation(models, start, fixed=[0], config=config)
        errors[per_scan] = absolute_trajectory_error(result.poses, sim.truth, align=False).rmse
    assert errors[0] < 0.01 and errors[8] < 1.3 * errors[0] + 0.002, errors


def _street(count: int, step: float, rng: np.random.Generator) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Scans every ``step`` metres down a 12 m wide street with no revisit: ground, two walls, and
    pillars at irregular spacing whose faces across the street hold each scan along it; each scan
    holds the surfaces within 25 m of it (1 cm noise, reduced to 0.1 m as the pipeline does)."""
    from slam6d.geometry import rot_z
    from slam6d.octree import reduce_points

    length = count * step + 40.0
    u = rng.random((int(length * 120), 2))
    parts = [np.c_[u[:, 0] * length - 20, u[:, 1] * 12 - 6, np.zeros(len(u))]]
    for side in (-6.0, 6.0):
        u = rng.random((int(length * 50), 2))
        parts.append(np.c_[u[:, 0] * length - 20, np.full(len(u), side), u[:, 1] * 5])
    for x in np.cumsum(rng.uniform(3.0, 9.0, int(length / 3))) - 20:
        pillar = rng.choice([-5.5, 5.5])
        for face in (x - 0.25, x + 0.25):
            u = rng.random((300, 2))
            parts.append(np.c_[np.full(len(u), face), pillar + u[:, 0] - 0.5, u[:, 1] * 3])
    world = np.vstack(parts) + rng.normal(0.0, 0.01, (sum(len(p) for p in parts), 3))
    truth = [make_pose(rot_z(0.0), [k * step, 0.3 * np.sin(k / 5.0), 1.5]) for k in range(count)]
    scans = []
    for pose in truth:
        seen = transform_points(invert(pose), world[np.linalg.norm(world[:, :2] - pose[:2, 3], axis=1) < 25.0])
        scans.append(seen[reduce_points(seen, 0.1)])
    return scans, truth


def test_lum_takes_a_heading_bend_out_of_an_open_street() -> None:
    """A heading error that registration built up a little per step, over a stretch no loop holds
    (the 1,000-scan campus of seed 5 ended 20 cm off that way), is what the relaxation's pairs
    between scans several steps apart are there to remove: here 0.01° per step over 40 scans,
    19 cm at the end. Levenberg damping in proportion to every scan's whole diagonal block held
    each scan to where it started: 12 mm were left after ten rounds. Damping only the directions
    a scan's pairs leave unconstrained takes the bend out in a few rounds."""
    from slam6d.geometry import rot_z

    scans, truth = _street(40, 3.0, np.random.default_rng(1))
    models = ScanModels(scans, ICPConfig(max_distance=0.25, max_iterations=30))
    bent = [truth[0]]
    for k in range(1, len(truth)):
        bent.append(bent[-1] @ make_pose(rot_z(np.radians(0.01)), np.zeros(3)) @ invert(truth[k - 1]) @ truth[k])
    assert absolute_trajectory_error(bent, truth, align=False).rmse > 0.15
    result = lum_relaxation(models, bent, fixed=[0], config=RelaxationConfig())
    left = absolute_trajectory_error(result.poses, truth, align=False).rmse
    assert left < 0.004 and result.iterations <= 4, (left, result.iterations)


def test_lum_damping_holds_only_the_directions_a_scan_leaves_unconstrained() -> None:
    """A scan whose pairs constrain every direction is not damped at all; one that sees a single
    flat wall (nothing along the wall, nor turning about its normal) is held in just those
    directions, by ``damping`` x its strongest information, whatever units it is measured in."""
    from slam6d.lum import _damped

    rng = np.random.default_rng(2)
    points = rng.normal(0.0, 5.0, (500, 3))
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    jacobian = np.hstack([normals, np.cross(points, normals)])
    full = jacobian.T @ jacobian
    wall = np.c_[np.zeros(500), rng.uniform(-5, 5, 500), rng.uniform(0, 3, 500)]  # the plane x = 0
    along = np.hstack([np.tile([1.0, 0.0, 0.0], (500, 1)), np.cross(wall, [1.0, 0.0, 0.0])])
    flat = along.T @ along
    damped = _damped(np.stack([full, flat]), 1e-3)
    np.testing.assert_allclose(damped[0], full, rtol=1e-9, atol=1e-9 * np.abs(full).max())
    added = damped[1] - flat
    assert np.linalg.matrix_rank(flat) == 3 and np.linalg.matrix_rank(damped[1]) == 6
    # nothing is added where the wall holds the scan: across it, and tilting it about y and z
    held = np.linalg.eigh(flat)[1][:, 3:]
    np.testing.assert_allclose(held.T @ added @ held, 0.0, atol=1e-9 * np.abs(flat).max())


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("coarse_fraction", 0.0),
        ("coarse_fraction", 3.0),
        ("coarse_chi2_tolerance", -0.1),
        ("acceleration_depth", -1),
        ("min_round_points", -5),
        ("steady_tolerance", float("nan")),
    ],
)
def test_a_thin_sample_setting_out_of_range_is_refused_naming_the_field(field: str, value: float) -> None:
    """A session's ``[engine] relax = {coarse_fraction = 3}`` would otherwise mean "every round on the
    full sample" without a word: the settings say which field is wrong instead."""
    with pytest.raises(SettingsError, match=field):
        pipeline_config({"relax": {field: value}})


def test_an_unknown_settle_rule_is_refused_naming_the_field() -> None:
    """``[engine] relax = {settle_on = "pairs"}`` names the field and the rules there are."""
    with pytest.raises(SettingsError, match=r"settle_on.*'cost' or 'movement'"):
        pipeline_config({"relax": {"settle_on": "pairs"}})


def test_the_trajectory_benchmark_takes_relaxation_settings_by_name() -> None:
    """``benchmarks/trajectory.py --balm --relax FIELD=VALUE`` reproduces docs/scale.md's BALM figures
    for other settings: values read as a session's ``[engine] relax`` would be, a wrong name named."""
    from benchmarks.trajectory import relax_settings

    assert relax_settings(["coarse_fraction=1.0", " max_rounds = 20", "tolerance=0"]) == RelaxationConfig(
        coarse_fraction=1.0, max_rounds=20, tolerance=0.0
    )
    with pytest.raises(SettingsError, match="coarse_fractio"):
        relax_settings(["coarse_fractio=1.0"])
    with pytest.raises(SystemExit, match="FIELD=VALUE"):
        relax_settings(["coarse_fraction"])


def test_every_pairs_own_sample_is_the_scans_thinned_copy_drawn_for_all_pairs_at_once() -> None:
    """A LUM budget gives every pair a sample size of its own; the samples, drawn for all pairs of a
    scan at once, are exactly the points ``ScanModels.thinned`` spreads over each scan (linspace
    from the first point to the last, rounded), a scan with fewer points than asked giving all."""
    rng = np.random.default_rng(2)
    points = [rng.normal(size=(size, 3)) for size in (1, 7, 250, 1001, 4000)]
    models = ScanModels(points, ICPConfig())
    others = [4, 0, 3, 1, 2, 3]
    counts = [333, 5, 1001, 7, 1, 2]  # over, at and under each scan's size; one point; two
    stacked, source = gathered(models, others, counts)
    expected = [models.thinned(j, c) for j, c in zip(others, counts, strict=True)]
    np.testing.assert_array_equal(stacked, np.concatenate(expected))
    np.testing.assert_array_equal(source, np.repeat(np.arange(len(others)), [len(e) for e in expected]))
    lengths, asked = np.array([1001, 4000, 250, 2]), np.array([1, 333, 249, 2])
    index, of = spread_evenly(lengths, asked)
    for k, (length, count) in enumerate(zip(lengths, asked, strict=True)):
        np.testing.assert_array_equal(index[of == k], np.linspace(0, length - 1, count).round().astype(np.int64))
