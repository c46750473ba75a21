"""The sparse pose-graph solver: the reduced Cholesky system against dense algebra and gtsam, and its failures."""

from __future__ import annotations

import numpy as np
import pytest

from slam6d.block_system import BlockSystem
from slam6d.errors import RelaxationError
from slam6d.geometry import invert, make_pose, so3_exp
from slam6d.posegraph import (
    PoseEdge,
    _chordal_rotations,
    _pack_edges,
    check_connected,
    optimize_pose_graph,
)


def _random_system(
    rng: np.random.Generator, count: int, pairs: list[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal-equation blocks of random positive definite edge terms, and the same matrix dense."""
    dense = np.zeros((6 * count, 6 * count))
    diag = np.zeros((count, 6, 6))
    off = np.zeros((len(pairs), 6, 6))
    for e, (i, j) in enumerate(pairs):
        a = rng.normal(size=(9, 12))
        h = a.T @ a
        diag[i] += h[:6, :6]
        diag[j] += h[6:, 6:]
        off[e] = h[:6, 6:]
        for (p, q), block in (((i, i), h[:6, :6]), ((i, j), h[:6, 6:]), ((j, i), h[6:, :6]), ((j, j), h[6:, 6:])):
            dense[6 * p : 6 * p + 6, 6 * q : 6 * q + 6] += block
    return diag, off, dense


def _loop_graph(rng: np.random.Generator, count: int, loops: int) -> list[PoseEdge]:
    """A noisy odometry chain with random loop edges, like the 10,000-pose benchmark but smaller."""
    truth = [np.eye(4)]
    for _ in range(count - 1):
        step = make_pose(so3_exp(rng.normal(0, 0.05, 3)), np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.05, 3))
        truth.append(truth[-1] @ step)
    info = np.diag([1 / 0.01**2] * 3 + [1 / 0.002**2] * 3)

    def noisy(i: int, j: int) -> PoseEdge:
        noise = make_pose(so3_exp(rng.normal(0, 0.002, 3)), rng.normal(0, 0.01, 3))
        return PoseEdge(i, j, invert(truth[i]) @ truth[j] @ noise, info)

    edges = [noisy(k, k + 1) for k in range(count - 1)]
    for _ in range(loops):
        i, j = sorted(rng.choice(count, 2, replace=False))
        edges.append(noisy(int(i), int(j)))
    return edges


def _chained(edges: list[PoseEdge], count: int) -> list[np.ndarray]:
    poses = [np.eye(4)]
    for edge in edges[: count - 1]:
        poses.append(poses[-1] @ edge.measurement)
    return poses


def test_reduced_cholesky_matches_dense_solves_as_values_change_on_one_pattern() -> None:
    """Many loop ends (fill between path ends, key-to-key and parallel edges, a fixed pose mid-chain):
    every solve on the same system, with new values each time, equals a dense solve of that matrix."""
    rng = np.random.default_rng(3)
    count = 80
    pairs = [(k, k + 1) for k in range(count - 1)]
    pairs += [(3, 40), (40, 3), (41, 70), (10, 11), (55, 12), (12, 13), (70, 71), (20, 60), (60, 61), (79, 0)]
    ei = np.array([i for i, _ in pairs])
    ej = np.array([j for _, j in pairs])
    fixed = {0, 30}
    system = BlockSystem(count, fixed, ei, ej)
    assert system.size >= 6 * 9 and len(system.interior) > count // 2
    free = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in range(count) if k not in fixed])
    for _ in range(3):
        diag, off, dense = _random_system(rng, count, pairs)
        rhs = rng.normal(size=(count, 6))
        want = np.zeros(6 * count)
        want[free] = np.linalg.solve(dense[np.ix_(free, free)], rhs.ravel()[free])
        got = system.solve(diag, off, rhs)
        np.testing.assert_allclose(got.ravel(), want, rtol=1e-8, atol=1e-10)


def _dense_loop_pairs(count: int, neighbours: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """A chain whose every pose also has ``neighbours`` partners all along it (a dense loop's LUM
    graph): no pose is interior, the reduced system is every free pose."""
    pairs = [(k, k + 1) for k in range(count - 1)]
    for k in range(count):
        for j in rng.choice(count, neighbours, replace=False):
            if abs(int(j) - k) > 1:
                pairs.append((k, int(j)))
    return pairs


def test_a_large_reduced_system_reuses_its_factor_and_still_equals_dense_solves() -> None:
    """Rounds of a relaxation over one pattern: the matrices differ by each edge's weight (Cauchy's,
    re-drawn pairs), and all but the first solve run on an earlier factor. Each step equals a dense
    solve of its own matrix; a matrix unlike the factored one (fresh random blocks) is refactored
    and solved as exactly; one that is singular is still reported as such."""
    rng = np.random.default_rng(11)
    count = 40
    pairs = _dense_loop_pairs(count, 4, rng)
    ei = np.array([i for i, _ in pairs])
    ej = np.array([j for _, j in pairs])
    system = BlockSystem(count, {0}, ei, ej, refactor_above=0)
    assert len(system.interior) == 0
    free = np.arange(6, 6 * count)

    def built(terms: list[np.ndarray], weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The blocks of edge e's 12x12 term weighted by weights[e], and the same matrix dense."""
        diag = np.zeros((count, 6, 6))
        dense = np.zeros((6 * count, 6 * count))
        for (i, j), term, weight in zip(pairs, terms, weights, strict=True):
            h = term * weight
            diag[i] += h[:6, :6]
            diag[j] += h[6:, 6:]
            for (a, b), block in (((i, i), h[:6, :6]), ((i, j), h[:6, 6:]), ((j, i), h[6:, :6]), ((j, j), h[6:, 6:])):
                dense[6 * a : 6 * a + 6, 6 * b : 6 * b + 6] += block
        off = np.array([term[:6, 6:] * weight for term, weight in zip(terms, weights, strict=True)])
        return diag, off, dense

    def check(terms: list[np.ndarray], weights: np.ndarray) -> None:
        """The system's solve equals the dense solve of the same matrix."""
        diag, off, dense = built(terms, weights)
        rhs = rng.normal(size=(count, 6))
        want = np.zeros(6 * count)
        want[free] = np.linalg.solve(dense[np.ix_(free, free)], rhs.ravel()[free])
        np.testing.assert_allclose(system.solve(diag, off, rhs).ravel(), want, rtol=1e-8, atol=1e-10)

    def random_terms(rows: int, scale: float) -> list[np.ndarray]:
        return [(lambda a: scale * a.T @ a)(rng.normal(size=(rows, 12))) for _ in pairs]

    terms = random_terms(9, 1.0)
    solves = 6
    for _ in range(solves):
        check(terms, rng.uniform(0.5, 2.0, len(pairs)))
    assert system.factorisations < solves  # the factor was reused
    held = system.factorisations
    check(random_terms(7, 100.0), np.ones(len(pairs)))  # another matrix entirely
    assert system.factorisations == held + 1  # too far from the factor held: refactored
    weights = np.ones(len(pairs))
    weights[(ei == 5) | (ej == 5)] = 0.0  # pose 5 unconstrained: every block of it gone
    diag, off, _ = built(terms, weights)
    with pytest.raises(RelaxationError, match="singular"):
        system.solve(diag, off, np.ones((count, 6)))


def test_singular_reduced_system_is_reported() -> None:
    """Every pose is a loop end, so the rank deficiency reaches the Cholesky of the reduced system."""
    count = 6
    pairs = [(k, k + 1) for k in range(count - 1)] + [(0, 2), (1, 3), (2, 4), (3, 5), (5, 0)]
    ei = np.array([i for i, _ in pairs])
    ej = np.array([j for _, j in pairs])
    system = BlockSystem(count, {0}, ei, ej)
    assert len(system.interior) == 0
    diag, off, _ = _random_system(np.random.default_rng(4), count, pairs)
    diag[4, 2, :] = diag[4, :, 2] = 0.0  # pose 4 unconstrained along z
    for e, (i, j) in enumerate(pairs):
        if i == 4:
            off[e, 2, :] = 0.0
        if j == 4:
            off[e, :, 2] = 0.0
    with pytest.raises(RelaxationError, match="singular"):
        system.solve(diag, off, np.ones((count, 6)))


def test_degenerate_information_on_a_loop_graph_fails_with_the_reason() -> None:
    rng = np.random.default_rng(5)
    edges = _loop_graph(rng, 60, 8)
    flat = np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 1.0])  # nothing constrains z anywhere
    edges = [PoseEdge(e.i, e.j, e.measurement, flat) for e in edges]
    with pytest.raises(RelaxationError, match=r"singular.*fewer than 6 degrees of freedom"):
        optimize_pose_graph(_chained(edges, 60), edges, fixed=[0])


def test_disconnected_loop_graph_fails_naming_the_loose_scans() -> None:
    rng = np.random.default_rng(6)
    edges = [e for e in _loop_graph(rng, 40, 6) if (e.i < 30) == (e.j < 30)]  # 30..39 cut loose
    with pytest.raises(RelaxationError, match=r"disconnected: 10 scan\(s\) \(30, 31, .*39\)"):
        optimize_pose_graph(_chained(_loop_graph(rng, 40, 0), 40), edges, fixed=[0])


def test_optimum_of_a_loop_graph_matches_gtsam() -> None:
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(7)
    count = 1500
    edges = _loop_graph(rng, count, 75)
    start = _chained(edges, count)
    ours = optimize_pose_graph(start, edges, fixed=[0])
    assert ours.converged and ours.residual_after < 1e-5 * ours.residual_before

    from benchmarks.trajectory import gtsam_problem

    graph, values = gtsam_problem(start, edges)
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-10)
    result = gtsam.GaussNewtonOptimizer(graph, values, params).optimize()

    assert ours.residual_after == pytest.approx(2 * graph.error(result), rel=1e-6)
    for k in range(0, count, 97):
        np.testing.assert_allclose(ours.poses[k], result.atPose3(k).matrix(), atol=1e-4)
    np.testing.assert_array_equal(np.array(ours.poses)[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (count, 1)))


def test_rotation_seed_is_exact_on_consistent_edges_and_skipped_near_the_optimum() -> None:
    rng = np.random.default_rng(8)
    count = 300
    truth = [np.eye(4)]
    for _ in range(count - 1):
        truth.append(truth[-1] @ make_pose(so3_exp(rng.normal(0, 0.2, 3)), rng.normal(0, 1.0, 3)))
    pairs = [(k, k + 1) for k in range(count - 1)] + [
        tuple(sorted(rng.choice(count, 2, replace=False))) for _ in range(20)
    ]
    exact = [
        PoseEdge(int(i), int(j), invert(truth[i]) @ truth[j], np.diag([1.0, 2.0, 3.0, 40.0, 50.0, 60.0]))
        for i, j in pairs
    ]
    drifted = np.array([_noisy_rotation(p, rng) for p in truth])
    drifted[0] = truth[0]
    free = np.ones(count, dtype=bool)
    free[0] = False
    seeded = _chordal_rotations(drifted[:, :3, :3], _pack_edges(exact, count), free)
    assert seeded is not None
    np.testing.assert_allclose(seeded, np.array(truth)[:, :3, :3], atol=1e-9)

    # re-relaxing a converged graph neither moves it nor costs more than the one confirming step
    edges = _loop_graph(rng, 400, 20)
    first = optimize_pose_graph(_chained(edges, 400), edges, fixed=[0])
    again = optimize_pose_graph(first.poses, edges, fixed=[0])
    assert again.iterations == 1
    assert again.residual_after == pytest.approx(first.residual_after, rel=1e-9)


def test_graph_whose_rotations_only_translations_fix_still_converges() -> None:
    """Translation-only information: the rotation seed is undetermined and left out, Gauss-Newton still solves it."""
    rng = np.random.default_rng(9)
    positions = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 5.0]])
    truth = [make_pose(so3_exp(rng.normal(0, 0.3, 3)), p) for p in positions]
    translation_only = np.diag([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    edges = [
        PoseEdge(i, j, invert(truth[i]) @ truth[j], translation_only) for i in range(4) for j in range(4) if i != j
    ]
    start = [truth[0]] + [p @ make_pose(so3_exp(rng.normal(0, 0.1, 3)), rng.normal(0, 0.2, 3)) for p in truth[1:]]
    free = np.array([False, True, True, True])
    assert _chordal_rotations(np.array(start)[:, :3, :3], _pack_edges(edges, 4), free) is None
    result = optimize_pose_graph(start, edges, fixed=[0])
    assert result.converged and result.residual_after < 1e-12
    for got, want in zip(result.poses, truth, strict=True):
        np.testing.assert_allclose(got, want, atol=1e-6)


def _noisy_rotation(pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return make_pose(pose[:3, :3] @ so3_exp(rng.normal(0, 0.3, 3)), pose[:3, 3])


def test_block_solver_with_eliminated_paths_matches_a_dense_solve() -> None:
    """Chain paths eliminated by the sweep, a fixed pose inside a path, a leaf, parallel edges, loops."""
    rng = np.random.default_rng(7)
    count = 40
    pairs = [(k, k + 1) for k in range(count - 1)] + [(5, 30), (31, 12), (12, 13), (20, 38)]
    fixed = {0, 17}
    system = BlockSystem(count, fixed, np.array([i for i, _ in pairs]), np.array([j for _, j in pairs]))
    assert len(system.interior) > 20 and 17 not in system.interior and 12 not in system.interior
    diag, off, dense = _random_system(rng, count, pairs)
    rhs = rng.normal(size=(count, 6))
    free = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in range(count) if k not in fixed])
    want = np.zeros(6 * count)
    want[free] = np.linalg.solve(dense[np.ix_(free, free)], rhs.ravel()[free])
    got = system.solve(diag, off, rhs)
    np.testing.assert_allclose(got.ravel(), want, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_check_connected_names_exactly_the_scans_with_no_path_to_a_fixed_one(seed: int) -> None:
    """Against a plain breadth-first search, on random sparse graphs with several components."""
    rng = np.random.default_rng(seed)
    count = 60
    edges = [tuple(int(v) for v in rng.choice(count, 2, replace=False)) for _ in range(45)]
    reached, frontier = {0}, [0]
    while frontier:
        node = frontier.pop()
        for a, b in edges:
            for here, there in ((a, b), (b, a)):
                if here == node and there not in reached:
                    reached.add(there)
                    frontier.append(there)
    loose = sorted(set(range(count)) - reached)
    if not loose:
        check_connected(count, edges, fixed=[0])
        return
    with pytest.raises(RelaxationError) as error:
        check_connected(count, edges, fixed=[0])
    shown = ", ".join(str(k) for k in loose[:12])
    assert f"disconnected: {len(loose)} scan(s) ({shown}" in str(error.value)
