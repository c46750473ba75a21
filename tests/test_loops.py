"""Loop hypotheses, verification and error diffusion."""

from __future__ import annotations

import numpy as np
import pytest

from slam6d.geometry import (
    invert,
    make_pose,
    pose_difference,
    pose_from_xyzrpy,
    rotation_angle,
    so3_exp,
    transform_points,
)
from slam6d.icp import ICPConfig
from slam6d.loops import (
    LoopConfig,
    LoopHypothesis,
    diffuse_loop_correction,
    find_loop_hypotheses,
    hold_closed_loops,
    loop_correction,
    octree_overlap,
    pair_fitness,
    path_lengths,
    usual_fit,
    verify,
)
from slam6d.metrics import absolute_trajectory_error
from slam6d.model import ModelIndex
from slam6d.octree import Octree, reduce_points
from slam6d.pipeline import Pipeline, PipelineConfig
from tests.simulated_loop import simulated_loop


def _ring(count: int, radius: float) -> list[np.ndarray]:
    angles = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    return [pose_from_xyzrpy(radius * np.cos(a), radius * np.sin(a), 0.0, 0.0, 0.0, a + np.pi / 2) for a in angles]


def test_hypotheses_come_from_poses_near_in_space_far_along_the_path() -> None:
    poses = _ring(20, 10.0)  # neighbours ~3.1 m apart, 63 m around
    found = find_loop_hypotheses(poses, max_range=30.0, config=LoopConfig(radius_fraction=0.25))
    pairs = {(h.i, h.j) for h in found}
    assert (0, 19) in pairs and (0, 18) in pairs
    assert all(h.j - h.i >= LoopConfig().min_index_gap for h in found)
    assert all(h.distance <= 7.5 and h.path_length >= 3 * h.distance for h in found)
    assert not find_loop_hypotheses(poses[:10], max_range=30.0)  # half a ring closes nothing
    assert {(h.i, h.j) for h in find_loop_hypotheses(poses, 30.0, last_only=1)} <= {(i, 19) for i in range(19)}


def test_diffusion_moves_scan_j_fully_and_earlier_scans_by_path_fraction() -> None:
    poses = _ring(12, 10.0)
    correction = make_pose(so3_exp(np.array([0.0, 0.0, 0.2])), np.array([0.5, -0.3, 0.1]))
    out = diffuse_loop_correction(poses, 2, 8, correction)
    for k in (0, 1, 2):
        np.testing.assert_allclose(out[k], poses[k])
    np.testing.assert_allclose(out[8], correction @ poses[8], atol=1e-12)
    for k in (9, 10, 11):  # after the loop: rigidly attached, so the trajectory stays continuous
        np.testing.assert_allclose(out[k], correction @ poses[k], atol=1e-12)
    travelled = path_lengths(poses)
    for k in range(3, 8):
        f = (travelled[k] - travelled[2]) / (travelled[8] - travelled[2])
        applied = out[k] @ invert(poses[k])
        assert rotation_angle(applied[:3, :3]) == pytest.approx(0.2 * f, abs=1e-9)
    # consecutive relative motions change smoothly: no jump anywhere
    steps = [pose_difference(invert(out[k]) @ out[k + 1], invert(poses[k]) @ poses[k + 1])[0] for k in range(11)]
    moved_j = float(np.linalg.norm(out[8][:3, 3] - poses[8][:3, 3]))
    assert max(steps) < 1.5 * moved_j / 6


def test_diffusion_rejects_bad_indices() -> None:
    with pytest.raises(ValueError, match="loop"):
        diffuse_loop_correction(_ring(5, 3.0), 3, 2, np.eye(4))


@pytest.fixture(scope="module")
def loop_scene():  # type: ignore[no-untyped-def]
    sim = simulated_loop(scans=10, points=20000, seed=7, loop_length=16.0, loop_width=10.0)
    points = [s.points[reduce_points(s.points, 0.1)] for s in sim.sequence]
    return sim, points


def test_verify_accepts_the_true_loop_from_a_drifted_start_and_rejects_a_wrong_one(loop_scene) -> None:  # type: ignore[no-untyped-def]
    sim, points = loop_scene
    truth = sim.truth
    drift = make_pose(so3_exp(np.array([0.0, 0.0, np.radians(2.0)])), np.array([0.35, -0.25, 0.05]))
    drifted = [p.copy() for p in truth]
    drifted[9] = drift @ truth[9]
    hyp = find_loop_hypotheses(drifted, 30.0, LoopConfig(min_path=5.0), last_only=1)
    loop = next(h for h in hyp if h.i == 0)
    occupancy = Octree(points[0], 0.5).occupancy(0.5)
    loop.overlap = octree_overlap(occupancy, points[9], loop.transform)
    assert loop.overlap >= LoopConfig().min_overlap
    verdict = verify(loop, ModelIndex(points[0]), points[9], ICPConfig())
    assert verdict.accepted, verdict.reason
    fixed = diffuse_loop_correction(drifted, 0, 9, loop_correction(drifted, verdict))
    dt, dr = pose_difference(fixed[9], truth[9])
    assert dt < 0.03 and np.degrees(dr) < 0.3
    # scan 4 lies across the block: placed where scan 9 is, ICP cannot make it fit
    wrong = LoopHypothesis(0, 4, 0.0, 20.0, transform=invert(truth[0]) @ truth[9])
    assert not verify(wrong, ModelIndex(points[0]), points[4], ICPConfig()).accepted
    far = octree_overlap(occupancy, points[9], make_pose(np.eye(3), [200.0, 0.0, 0.0]))
    assert far == 0.0


@pytest.mark.parametrize("points", [6000, 20000])
def test_verify_rejects_an_ambiguous_sparse_loop_and_accepts_the_same_loop_when_dense(points: int) -> None:
    """The workbench's 8-scan loop (``tests.session_fixtures.write_loop_scans``) from its drifting odometry.

    With 6,000 points per scan the 0-7 overlap is mostly floor: ICP found fitness 0.33 and RMS
    0.13 m at a transform metres off, and used to accept it. With 20,000 points the same loop
    from the same start is pinned down and must be accepted, close to the truth.
    """
    sim = simulated_loop(scans=8, points=points, seed=1, loop_length=16.0, loop_width=10.0)
    cloud = [s.points[reduce_points(s.points, 0.1)] for s in sim.sequence]
    odometry = [s.pose for s in sim.sequence]
    start = invert(odometry[0]) @ odometry[7]
    truth = invert(sim.truth[0]) @ sim.truth[7]
    assert pose_difference(start, truth)[0] > 1.0  # the loop really has to be closed
    hypothesis = LoopHypothesis(0, 7, 1.0, 46.0, transform=start)
    verdict = verify(hypothesis, ModelIndex(cloud[0]), cloud[7], ICPConfig(data_voxel_size=0.0))
    dt, dr = pose_difference(verdict.transform, truth)
    if points == 6000:
        assert not verdict.accepted and "pin down the translation" in verdict.reason, verdict.reason
        assert dt > 0.3  # what the old verification accepted
        # the restarts alone catch it too: ICP shifted along the weakest direction ends elsewhere
        alone = verify(
            hypothesis, ModelIndex(cloud[0]), cloud[7], ICPConfig(data_voxel_size=0.0), LoopConfig(min_constraint=0)
        )
        assert not alone.accepted and "ambiguous" in alone.reason and alone.disagreement > 0.3, alone.reason
    else:
        assert verdict.accepted, verdict.reason
        assert verdict.constraint >= LoopConfig().min_constraint and verdict.disagreement < 0.05
        assert dt < 0.02 and np.degrees(dr) < 0.5, (dt, np.degrees(dr))


@pytest.fixture(scope="module")
def campus_ramp():  # type: ignore[no-untyped-def]
    """The simulated campus (car VLP-16, the benchmark's seed) up to its first revisit: the car goes up
    the parking deck's ramp, round the roof and down the same ramp (scans ~30-111)."""
    sim = simulated_loop(scans=250, points=20000, seed=3, world="campus", first=111)
    return sim, [s.points[reduce_points(s.points, 0.1)] for s in sim.sequence]


def _drifted(truth: list[np.ndarray], per_step: np.ndarray) -> list[np.ndarray]:
    """The true trajectory with every relative motion turned a little more: a smooth rotational drift
    like sequential registration's (roll/pitch/yaw per step, radians)."""
    turn = make_pose(so3_exp(per_step), np.zeros(3))
    poses = [truth[0].copy()]
    for k in range(1, len(truth)):
        poses.append(poses[-1] @ invert(truth[k - 1]) @ truth[k] @ turn)
    return poses


def test_campus_revisit_drifted_beyond_the_old_gates_is_closed(campus_ramp) -> None:  # type: ignore[no-untyped-def]
    """Down the ramp after 140 m of path, drifted ~1.7 m / 2.3°: the pose-implied start overlaps the
    earlier scan far under the old fixed 0.2 gate and correct VLP-16 fits pair under the old 0.3
    fitness; judged against the sequence's own consecutive pairs the loop is verified within a few
    centimetres, and closing it brings the trajectory back near the truth."""
    sim, points = campus_ramp
    truth = sim.truth
    drifted = _drifted(truth, np.array([0.0003, 0.0004, 0.0005]))
    config = LoopConfig()
    cube = config.overlap_cube
    octrees = {k: Octree(points[k], cube).occupancy(cube) for k in range(len(points))}
    candidates = find_loop_hypotheses(drifted, 32.0, config, octrees.__getitem__, points, last_only=1)
    assert candidates and all(h.j == 110 for h in candidates)
    loop = candidates[0]
    assert loop.start_overlap < LoopConfig().min_overlap  # the old gate refused it before any match
    icp_config = ICPConfig()
    usual = usual_fit(
        truth,  # registered consecutive pairs sit where registration put them: near the truth
        octrees.__getitem__,
        points,
        lambda k: pair_fitness(ModelIndex(points[k - 1]), points[k], invert(truth[k - 1]) @ truth[k], 0.25),
    )
    assert usual is not None
    verdict = verify(loop, ModelIndex(points[loop.i]), points[loop.j], icp_config, config, usual)
    assert verdict.accepted, verdict.reason
    assert verdict.fitness < LoopConfig().min_fitness  # the old fixed bar refused correct fits too
    dt, dr = pose_difference(verdict.transform, invert(truth[loop.i]) @ truth[loop.j])
    assert dt < 0.05 and np.degrees(dr) < 0.6, (dt, np.degrees(dr))
    before = absolute_trajectory_error(drifted, truth).rmse
    closed = diffuse_loop_correction(drifted, loop.i, loop.j, loop_correction(drifted, verdict))
    after = absolute_trajectory_error(closed, truth).rmse
    assert before > 0.4 and after < 0.25, (before, after)


def test_campus_ramp_revisits_close_right_against_the_fused_neighbourhood(campus_ramp) -> None:  # type: ignore[no-untyped-def]
    """The ramp's revisits (scans ~95-110 against ~29-46, most from the opposite direction), closed by
    the pipeline's own loop stage after its sequential registration.

    Against scan i's VLP-16 rings alone a revisit paired under a bar scaled by registration's
    fitness against its fused metascan: 19 of 20 tried were refused (fitness 0.10-0.16 under 0.18),
    though many were right to 2-3 cm, and all were 0.1-0.55° off the true relative tilt (the rings'
    own planes; the one closed 0.21°). Verified against scan i fused with its neighbours, as
    registration matched, every tried revisit closes (measured: 5 of 5) and each is right to
    3.4 cm and 0.13° (asked: 5 cm and 0.2°); with pairs kept to the face each scanner saw
    (:meth:`slam6d.model.ModelIndex.plane_pairs`) 5 of 5, 3.1 cm and 0.13°."""
    sim, _ = campus_ramp
    pipeline = Pipeline(sim.sequence, PipelineConfig(relaxation="none"))
    pipeline.run()
    tried = pipeline.loops
    closed = [h for h in tried if h.accepted]
    assert len(closed) >= 3 and len(closed) == len(tried), [(h.i, h.j, h.reason) for h in tried]
    for loop in closed:
        assert loop.transform is not None
        dt, dr = pose_difference(loop.transform, invert(sim.truth[loop.i]) @ sim.truth[loop.j])
        assert dt < 0.05 and np.degrees(dr) < 0.2, (loop.i, loop.j, dt, np.degrees(dr))


def test_holding_closed_loops_keeps_an_earlier_loop_that_a_later_closing_breaks() -> None:
    """Twice round a ring with a pitch and heading drift, closed at (5, 45) and then at (20, 60).

    Error diffusion moves only the scans after a loop's scan i, so the second closing carries scan
    45 away from scan 5 again (the campus: loops 2 m apart in height after 51 closings, out of the
    relaxation's reach). Held as one pose graph with the registered steps, both loops hold and the
    scans before the first loop stay where they were."""
    truth = _ring(40, 20.0)
    truth = truth + [t.copy() for t in truth]  # scan k + 40 revisits scan k
    drifted = _drifted(truth, np.array([0.0, np.radians(0.1), np.radians(0.05)]))
    loops = [
        LoopHypothesis(5, 45, 0.0, 0.0, transform=invert(truth[5]) @ truth[45]),
        LoopHypothesis(20, 60, 0.0, 0.0, transform=invert(truth[20]) @ truth[60]),
    ]
    diffused, held = drifted, drifted
    for n, loop in enumerate(loops):
        diffused = diffuse_loop_correction(diffused, loop.i, loop.j, loop_correction(diffused, loop))
        start = diffuse_loop_correction(held, loop.i, loop.j, loop_correction(held, loop))
        held = hold_closed_loops(drifted, loops[: n + 1], start, lever=10.0)

    def mismatch(poses: list[np.ndarray], loop: LoopHypothesis) -> tuple[float, float]:
        assert loop.transform is not None
        dt, dr = pose_difference(invert(poses[loop.i]) @ poses[loop.j], loop.transform)
        return dt, float(np.degrees(dr))

    assert mismatch(diffused, loops[0])[0] > 0.1  # the later closing broke the earlier loop
    for loop in loops:
        dt, dr = mismatch(held, loop)
        assert dt < 0.01 and dr < 0.1, (loop.i, loop.j, dt, dr)
    for k in range(6):
        np.testing.assert_allclose(held[k], drifted[k], atol=1e-6)
    assert absolute_trajectory_error(held, truth).rmse < absolute_trajectory_error(diffused, truth).rmse


def _colonnade(column_x: np.ndarray, heights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A street between two rows of columns (0.5 m square, at y = ±5 m) over a ground plane: points
    on the columns' faces and the ground, world frame."""
    parts = [np.column_stack([rng.uniform(-40, 80, 40000), rng.uniform(-8, 8, 40000), np.zeros(40000)])]
    for x, height in zip(column_x, heights, strict=True):
        for y in (-5.0, 5.0):
            face = rng.uniform(-0.25, 0.25, (400, 2))
            z = rng.uniform(0.0, height, 400)
            for side in (0, 1):  # the faces across x and across y
                offset = np.where(rng.random(200) < 0.5, -0.25, 0.25)
                if side == 0:
                    parts.append(np.column_stack([x + offset, y + face[:200, 1], z[:200]]))
                else:
                    parts.append(np.column_stack([x + face[200:, 0], y + offset, z[200:]]))
    return np.vstack(parts)


def _seen_from(scene: np.ndarray, pose: np.ndarray, reach: float = 25.0) -> np.ndarray:
    local = transform_points(invert(pose), scene)
    kept = local[np.linalg.norm(local[:, :2], axis=1) < reach]
    return kept[reduce_points(kept, 0.1)]


@pytest.mark.parametrize("repetitive", [True, False])
def test_a_loop_between_places_only_repetitive_structure_tells_apart_is_refused(repetitive: bool) -> None:
    """Scan j stands one column spacing (3.2 m) further down the street than scan i, but drift puts it
    0.4 m from scan i. Where the columns repeat exactly, ICP from that start lands on the next column
    (a perfect fit 2.8 m from the truth); the search about the match finds an equally good placement
    one period away, and the loop is refused as ambiguous. With the same street's columns spaced
    irregularly the loop is accepted at the true placement."""
    rng = np.random.default_rng(5)
    if repetitive:
        column_x = np.arange(-40.0, 80.0, 3.2)
        heights = np.full(len(column_x), 3.0)
    else:
        column_x = np.cumsum(rng.uniform(2.0, 7.0, 30)) - 40.0
        heights = rng.uniform(1.5, 4.0, len(column_x))
    scene = _colonnade(column_x, heights, rng)
    pose_i, pose_j = make_pose(np.eye(3), [0.0, 0.0, 1.8]), make_pose(np.eye(3), [3.2, 0.0, 1.8])
    cloud_i, cloud_j = _seen_from(scene, pose_i), _seen_from(scene, pose_j)
    # j as drift placed it relative to i: 0.4 m from scan i where the columns repeat (so the next
    # column is nearer than the truth), 0.4 m short of the truth where they do not
    start = make_pose(np.eye(3), [0.4 if repetitive else 2.8, 0.0, 0.0])
    hypothesis = LoopHypothesis(0, 60, 0.4, 100.0, transform=start)
    verdict = verify(hypothesis, ModelIndex(cloud_i), cloud_j, ICPConfig())
    truth = invert(pose_i) @ pose_j
    dt, _ = pose_difference(verdict.transform, truth)
    if repetitive:
        assert not verdict.accepted and "ambiguous" in verdict.reason and "repetitive" in verdict.reason, verdict.reason
        assert verdict.ambiguity > LoopConfig().ambiguity
        assert dt > 2.0  # what would have been accepted: the neighbouring column
        unguarded = verify(hypothesis, ModelIndex(cloud_i), cloud_j, ICPConfig(), LoopConfig(ambiguity=1.0))
        assert unguarded.accepted, unguarded.reason  # no other test notices
    else:
        assert verdict.accepted, verdict.reason
        assert verdict.ambiguity < LoopConfig().ambiguity and dt < 0.05, (verdict.ambiguity, dt)


def test_diffusion_removes_the_height_bulge_of_a_pitch_drift() -> None:
    """A loop's correction reaches the middle of the path in height and pitch, not only at scan j.

    130 m along an arc of 100 m radius, every registered step tilted by the same 0.1° of pitch:
    the height error grows with the square of the distance, 3.9 m at the end. Spread by turning
    each scan rigidly about scan i by its share, the correction left 1.1 m of it in the middle of
    the path; with each step's tilt turned back where it arose, no scan stays more than a few
    centimetres off the flat truth."""
    truth = _ring(200, 100.0)[:42]
    drifted = _drifted(truth, np.array([0.0, np.radians(0.1), 0.0]))
    heights = np.array([abs(d[2, 3] - t[2, 3]) for d, t in zip(drifted, truth, strict=True)])
    assert heights.max() > 3.5 and heights[21] > 1.0  # metres of vertical drift, a metre mid-way
    loop = LoopHypothesis(0, 41, 0.0, 130.0, transform=invert(truth[0]) @ truth[41])
    closed = diffuse_loop_correction(drifted, 0, 41, loop_correction(drifted, loop))
    np.testing.assert_allclose(closed[41], truth[41], atol=1e-9)
    vertical = [abs(c[2, 3] - t[2, 3]) for c, t in zip(closed, truth, strict=True)]
    assert max(vertical) < 0.1, max(vertical)
    assert absolute_trajectory_error(closed, truth).rmse < 0.06


def test_closing_loop_after_loop_keeps_every_pose_rigid() -> None:
    """A drive that revisits a place every few dozen scans, each revisit closed as the loop stage
    closes it: the correction is computed from the current poses (``loop_correction``), so any
    rounding left in a rotation after one closing is squared into the next. Applied raw to every
    later scan, it grew about tenfold per closing and a 1,000-scan campus ended with rotations 1.3
    off orthonormal (eval refused the poses, relaxation found the tail disconnected); every closed
    pose must stay a rotation."""
    rng = np.random.default_rng(0)
    step = make_pose(so3_exp(np.array([0.001, 0.002, 0.05])), [1.0, 0.0, 0.01])
    poses = [np.eye(4)]
    for _ in range(400):
        poses.append(poses[-1] @ step)
    for n in range(40):
        j = 9 * n + 20
        i = max(0, j - int(rng.integers(15, 60)))
        nudge = make_pose(so3_exp(np.array([0.0, 0.0, rng.normal(0, 0.01)])), rng.normal(0, 0.05, 3))
        loop = LoopHypothesis(i=i, j=j, distance=0.0, path_length=0.0, transform=invert(poses[i]) @ poses[j] @ nudge)
        poses = diffuse_loop_correction(poses, i, j, loop_correction(poses, loop))
    worst = max(float(np.abs(p[:3, :3] @ p[:3, :3].T - np.eye(3)).max()) for p in poses)
    assert worst < 1e-12
    assert all(np.linalg.det(p[:3, :3]) > 0 for p in poses)
