"""Sparse least-squares pose graph: the linear algebra behind LUM-style global relaxation.

Each edge says "scan j sits at ``measurement`` in scan i's frame, with this 6x6 information". The
solver minimises ``sum e^T Ω e`` over all poses with Gauss-Newton (Levenberg damping only when a
step would increase the error), building the Jacobians for every edge at once with numpy and
solving the sparse normal equations with a sparse Cholesky (CHOLMOD) whose ordering and symbolic
analysis are done once per graph, as the pattern never changes between iterations, and with
drifted rotations seeded by a linear chordal estimate first. That relaxes a 10,000-pose graph
with 500 loops in well under half a second on two cores, without a compiled graph library.

Error of an edge, with poses X = (R, t):
    e_t = R_i^T (t_j - t_i) - t_z          (translation, in scan i's frame)
    e_r = Log(R_z^T R_i^T R_j)             (rotation, right-perturbation of scan j)
and the update R <- R Exp(φ), t <- t + R ρ. The Jacobians below are exact (including the inverse
right Jacobian of SO(3)), so the converged poses are the true least-squares optimum.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import cvxopt
import numba
import numpy as np
from cvxopt import cholmod
from numpy.typing import NDArray

from slam6d.attitude import TiltPrior, measured_ups, tilt_information
from slam6d.block_system import BlockSystem
from slam6d.errors import DisconnectedGraphError, RelaxationError
from slam6d.geometry import Matrix, invert, skew, so3_exp, so3_log


@dataclass(frozen=True)
class PoseEdge:
    """A relative-pose constraint: ``measurement`` = inv(X_i) @ X_j, information ordered (translation, rotation)."""

    i: int
    j: int
    measurement: Matrix
    information: Matrix = field(default_factory=lambda: np.eye(6))


@dataclass
class PoseGraphResult:
    poses: list[Matrix]
    residual_before: float  # chi^2 = sum e^T Ω e at the start
    residual_after: float
    iterations: int
    converged: bool
    # per-edge translation / rotation error after optimisation (metres, radians), for reports
    edge_translation_error: list[float] = field(default_factory=list)
    edge_rotation_error: list[float] = field(default_factory=list)


# ---------------------------------------------------------------- SO(3) Jacobian


def _inverse_right_jacobian(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    k = skew(phi)
    small = theta < 1e-5
    safe = np.where(small, 1.0, theta)
    coef = np.where(
        small, 1.0 / 12.0, 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(np.where(small, 1.0, safe)))
    )
    return np.eye(3) + 0.5 * k + coef * (k @ k)


# ---------------------------------------------------------------- the solver


@dataclass
class _Edges:
    i: NDArray[np.int64]
    j: NDArray[np.int64]
    rz: NDArray[np.float64]
    tz: NDArray[np.float64]
    info: NDArray[np.float64]


def _pack_edges(edges: Sequence[PoseEdge], count: int) -> _Edges:
    if not edges:
        raise RelaxationError("the pose graph has no edges: no scan overlaps another enough to relate them")
    i = np.array([e.i for e in edges], dtype=np.int64)
    j = np.array([e.j for e in edges], dtype=np.int64)
    bad = (i < 0) | (i >= count) | (j < 0) | (j >= count) | (i == j)
    if bad.any():
        k = int(np.argmax(bad))
        raise RelaxationError(f"edge {k} ({i[k]}->{j[k]}) refers to a missing scan or to itself ({count} poses)")
    meas = np.array([e.measurement for e in edges], dtype=np.float64)
    info = np.array([e.information for e in edges], dtype=np.float64)
    if not (np.isfinite(meas).all() and np.isfinite(info).all()):
        raise RelaxationError("an edge has a non-finite measurement or information matrix")
    info = 0.5 * (info + np.transpose(info, (0, 2, 1)))
    return _Edges(i, j, meas[:, :3, :3], meas[:, :3, 3], info)


@numba.njit(cache=True)
def _components(count, first, second):  # type: ignore[no-untyped-def]
    """Connected-component label of every node (union-find with path halving).

    Compiled rather than scipy's csgraph: importing scipy.sparse alone costs ~0.2 s, a tenth of a
    whole run of ``slam6d run`` on a small session."""
    parent = np.arange(count)
    for k in range(len(first)):
        a, b = first[k], second[k]
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        while parent[b] != b:
            parent[b] = parent[parent[b]]
            b = parent[b]
        if a != b:
            parent[max(a, b)] = min(a, b)
    labels = np.empty(count, dtype=np.int64)
    for k in range(count):
        root = k
        while parent[root] != root:
            root = parent[root]
        labels[k] = root
    return labels


EdgePairs = Iterable[tuple[int, int]] | NDArray[np.int64]


def _labels(count: int, edge_pairs: EdgePairs) -> NDArray[np.int64]:
    pairs = np.asarray(edge_pairs if isinstance(edge_pairs, np.ndarray) else list(edge_pairs), dtype=np.int64)
    pairs = pairs.reshape(-1, 2)
    return _components(count, np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1]))


def connected_components(count: int, edge_pairs: EdgePairs) -> list[list[int]]:
    """The scans of each connected component (sorted), components ordered by their first scan."""
    labels = _labels(count, edge_pairs)
    groups: dict[int, list[int]] = {}
    for k, label in enumerate(labels.tolist()):
        groups.setdefault(label, []).append(k)
    return sorted(groups.values(), key=lambda group: group[0])


def describe_components(components: Sequence[Sequence[int]], limit: int = 8) -> str:
    """``0-7, 8-29`` style summary: runs of consecutive scans collapsed, at most ``limit`` components."""

    def runs(group: Sequence[int]) -> str:
        parts: list[str] = []
        start = prev = group[0]
        for k in [*group[1:], None]:
            if k is not None and k == prev + 1:
                prev = k
                continue
            parts.append(str(start) if start == prev else f"{start}-{prev}")
            if k is not None:
                start = prev = k
        return ",".join(parts)

    shown = "; ".join(f"[{runs(group)}]" for group in components[:limit])
    return shown + (f"; ... ({len(components)} in all)" if len(components) > limit else "")


def check_connected(count: int, edge_pairs: EdgePairs, fixed: Iterable[int]) -> None:
    """Every pose must be tied to a fixed pose through edges, or its position is undetermined.

    ``edge_pairs`` may be an (edges, 2) array, which spares a large graph the round trip through
    tuples. Raises :class:`DisconnectedGraphError` naming every component otherwise.
    """
    labels = _labels(count, edge_pairs)
    anchored = [int(labels[f]) for f in fixed]
    loose = np.flatnonzero(~np.isin(labels, anchored)).tolist()
    if loose:
        shown = ", ".join(str(k) for k in loose[:12]) + (" ..." if len(loose) > 12 else "")
        components = connected_components(count, edge_pairs)
        raise DisconnectedGraphError(
            f"the pose graph is disconnected: {len(loose)} scan(s) ({shown}) share no edge path with a fixed scan "
            f"(components {describe_components(components)}); they do not overlap the rest enough "
            "(more point pairs, a larger max distance or odometry edges needed)",
            components,
        )


def _errors(rot: NDArray, trans: NDArray, e: _Edges) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    ri, rj = rot[e.i], rot[e.j]
    rij = np.matmul(np.transpose(ri, (0, 2, 1)), rj)  # batched matmul: several times faster than einsum here
    tij = np.einsum("mki,mk->mi", ri, trans[e.j] - trans[e.i])
    et = tij - e.tz
    er = so3_log(np.matmul(np.transpose(e.rz, (0, 2, 1)), rij))
    return np.concatenate([et, er], axis=1), rij, tij, er


def _chi2(err: NDArray, info: NDArray) -> float:
    return float(np.sum(err * np.matmul(info, err[:, :, None])[:, :, 0]))


def optimize_pose_graph(
    poses: Sequence[Matrix],
    edges: Sequence[PoseEdge],
    fixed: Iterable[int] = (0,),
    max_iterations: int = 30,
    tolerance: float = 1e-6,
    progress: Callable[[int, float], None] | None = None,
    tilt: TiltPrior | None = None,
) -> PoseGraphResult:
    """Least-squares poses for a graph of relative measurements; ``fixed`` poses do not move.

    Gauss-Newton, with Levenberg damping only when a step would raise χ². When the start's
    rotations are far off (drift), they are first replaced by the chordal estimate from the
    rotation constraints alone (:func:`_chordal_rotations`), which spares the iterations that would
    only turn them. It stops when an iteration lowers χ² by less than ``tolerance`` times its
    value, or when the step delivered the decrease its linear model promised to within that
    much: the next step could only gain about as little (quadratic convergence), so the
    factorisation that would merely confirm convergence is saved. ``residual_before`` is the χ²
    of the given poses. Raises :class:`RelaxationError` on a disconnected graph, on non-finite input, or when the
    normal equations are singular (a pose constrained in fewer than 6 degrees of freedom).

    ``tilt`` (:class:`slam6d.attitude.TiltPrior`): measured up per scan, a prior on each free pose's
    roll and pitch weighing the scan's ratio x the median tilt information of the consecutive edges
    (j = i + 1, the registration's steps; every edge where there are none), counted in χ².
    """
    count = len(poses)
    fixed_set = {int(f) for f in fixed}
    if not fixed_set:
        raise RelaxationError("no fixed pose: the graph's absolute position would be undetermined (fix scan 0)")
    if any(f < 0 or f >= count for f in fixed_set):
        raise RelaxationError(f"fixed pose index out of range for {count} poses: {sorted(fixed_set)}")
    packed = _pack_edges(edges, count)
    check_connected(count, np.stack([packed.i, packed.j], axis=1), fixed_set)

    stack = np.array(poses, dtype=np.float64)
    rot, trans = stack[:, :3, :3].copy(), stack[:, :3, 3].copy()
    system = BlockSystem(count, fixed_set, packed.i, packed.j)
    free = system.free

    tilt_weights = np.zeros(count) if tilt is None else _tilt_weights(tilt, packed, rot)

    def prior(rotations: NDArray) -> tuple[NDArray, NDArray, float]:
        if tilt is None:
            return np.zeros((count, 3, 3)), np.zeros((count, 3)), 0.0
        return tilt.terms(rotations, free, tilt_weights)

    err, rij, tij, er = _errors(rot, trans, packed)
    chi2 = _chi2(err, packed.info) + prior(rot)[2]
    before = chi2
    if max_iterations > 0 and free.any():
        seeded = _chordal_rotations(rot, packed, free)
        # only where the start's rotations are far off (drift): near the optimum the chordal
        # estimate, which ignores the translations, would be the worse start
        if seeded is not None and _rotation_chi2(seeded, packed) < _SEED_GAIN * _rotation_chi2(rot, packed):
            rot = seeded
            err, rij, tij, er = _errors(rot, trans, packed)
            chi2 = _chi2(err, packed.info) + prior(rot)[2]
    damping = 0.0
    converged = not free.any()
    iteration = 0
    while not converged and iteration < max_iterations:
        iteration += 1
        diag, off, gradient = _normal_blocks(packed, rij, tij, er, err, count)
        tilt_blocks, tilt_gradient, _ = prior(rot)
        diag[:, 3:, 3:] += tilt_blocks
        gradient[:, 3:] += tilt_gradient
        while True:
            damped = diag
            if damping > 0.0:
                scale = np.einsum("nii->ni", diag) * damping + 1e-9
                damped = diag + scale[:, :, None] * np.eye(6)
            step = system.solve(damped, off, -gradient)
            new_rot, new_trans = _moved(rot, trans, step, free)
            new_err, new_rij, new_tij, new_er = _errors(new_rot, new_trans, packed)
            new_chi2 = _chi2(new_err, packed.info) + prior(new_rot)[2]
            if new_chi2 <= chi2 * (1.0 + 1e-12) or damping > 1e8:
                break
            damping = 1e-4 if damping == 0.0 else damping * 10.0
        improvement = chi2 - new_chi2
        # the linear model's promise -g·δ; where the step kept it to within a sliver of χ², the
        # next step can only gain about that much (quadratic convergence), so stop already now
        mismatch = abs(improvement - float(-(gradient * step).sum()))
        rot, trans, err, rij, tij, er, chi2 = new_rot, new_trans, new_err, new_rij, new_tij, new_er, new_chi2
        damping = damping / 10.0 if damping > 1e-6 else 0.0
        if progress is not None:
            progress(iteration, chi2)
        limit = tolerance * max(chi2, 1e-300)
        converged = improvement <= limit or mismatch <= limit or float(np.abs(step).max()) < 1e-10
    stack[:, :3, :3], stack[:, :3, 3], stack[:, 3] = rot, trans, (0.0, 0.0, 0.0, 1.0)
    result_poses = list(stack)
    return PoseGraphResult(
        poses=result_poses,
        residual_before=before,
        residual_after=chi2,
        iterations=iteration,
        converged=converged,
        edge_translation_error=np.linalg.norm(err[:, :3], axis=1).tolist(),
        edge_rotation_error=np.linalg.norm(err[:, 3:], axis=1).tolist(),
    )


def _tilt_weights(tilt: TiltPrior, e: _Edges, rot: NDArray) -> NDArray:
    """:meth:`slam6d.attitude.TiltPrior.weights` over the consecutive edges' information on the
    later pose's tilt (information is ordered translation, rotation)."""
    steps = np.flatnonzero(e.j == e.i + 1)
    steps = steps if len(steps) else np.arange(len(e.i))
    order = np.array([3, 4, 5, 0, 1, 2])
    return tilt.weights(tilt_information(e.info[steps][:, order][:, :, order], measured_ups(rot[e.j[steps]])))


_SEED_GAIN = 0.1  # seed the rotations when that cuts their share of χ² at least tenfold


def _rotation_chi2(rot: NDArray, e: _Edges) -> float:
    """The rotational share of χ², e_r^T Ω_rr e_r summed over the edges."""
    er = so3_log(np.matmul(np.transpose(e.rz, (0, 2, 1)), np.matmul(np.transpose(rot[e.i], (0, 2, 1)), rot[e.j])))
    return _chi2(er, e.info[:, 3:, 3:])


def _chordal_rotations(rot: NDArray, e: _Edges, free: NDArray[np.bool_]) -> NDArray | None:
    """Rotations that best satisfy R_j = R_i R_z alone in the Frobenius norm, projected onto SO(3).

    Gauss-Newton from a drifted start (odometry chained over thousands of poses) spends most of
    its iterations turning the rotations, which enter the errors nonlinearly; this relaxation of
    the rotation constraints is linear and lands close to the optimum's rotations, after which the
    translations are nearly linear too (a 10,000-pose graph: 3 iterations instead of 5). Each row
    of R_j is that row of R_i times R_z, so the three rows share one 3x3-block system (weights: the
    mean rotational information of each edge), factored once by CHOLMOD. None when the rotation
    constraints alone leave some free rotation undetermined.
    """
    weight = np.trace(e.info[:, 3:, 3:], axis1=1, axis2=2) / 3.0
    index = -np.ones(len(rot), dtype=np.int64)
    index[free] = np.arange(int(free.sum()))
    fi, fj = free[e.i], free[e.j]
    size = 3 * int(free.sum())
    block = np.arange(3)
    # diagonal: w I at both free ends
    node = np.bincount(
        np.concatenate([index[e.i[fi]], index[e.j[fj]]]), np.concatenate([weight[fi], weight[fj]]), minlength=size // 3
    )
    rows = [(3 * np.arange(len(node))[:, None] + block).ravel()]
    cols = [rows[0]]
    values = [np.repeat(node, 3)]
    # off-diagonal, lower triangle: -w R_z^T at (j, i) when j > i, else its transpose -w R_z at (i, j)
    both = np.flatnonzero(fi & fj)
    low, high = np.minimum(index[e.i[both]], index[e.j[both]]), np.maximum(index[e.i[both]], index[e.j[both]])
    coupling = -weight[both, None, None] * e.rz[both]
    coupling = np.where(
        (index[e.j[both]] > index[e.i[both]])[:, None, None], np.transpose(coupling, (0, 2, 1)), coupling
    )
    rows.append((3 * high[:, None, None] + block[:, None]).repeat(3, axis=2).ravel())
    cols.append((3 * low[:, None, None] + block[None, :]).repeat(3, axis=1).ravel())
    values.append(coupling.ravel())
    # right-hand sides X_k = R_k^T (its columns are the rows of R_k), fixed ends moved over
    rhs = np.zeros((size // 3, 3, 3))
    to_j = np.flatnonzero(fj & ~fi)  # rhs_j += w R_z^T X_i
    np.add.at(
        rhs,
        index[e.j[to_j]],
        weight[to_j, None, None] * np.transpose(e.rz[to_j], (0, 2, 1)) @ rot[e.i[to_j]].transpose(0, 2, 1),
    )
    to_i = np.flatnonzero(fi & ~fj)  # rhs_i += w R_z X_j
    np.add.at(rhs, index[e.i[to_i]], weight[to_i, None, None] * e.rz[to_i] @ rot[e.j[to_i]].transpose(0, 2, 1))
    matrix = cvxopt.spmatrix(
        cvxopt.matrix(np.concatenate(values)),
        cvxopt.matrix(np.concatenate(rows)),
        cvxopt.matrix(np.concatenate(cols)),
        (size, size),
    )
    factor = cholmod.symbolic(matrix, uplo="L")
    try:
        cholmod.numeric(matrix, factor)
    except ArithmeticError:
        return None
    solution = cvxopt.matrix(np.asfortranarray(rhs.reshape(size, 3)))
    cholmod.solve(factor, solution)
    rotations, proper = _nearest_rotations(
        np.ascontiguousarray(np.asarray(solution).reshape(-1, 3, 3).transpose(0, 2, 1))
    )
    if not proper:
        return None
    seeded = rot.copy()
    seeded[free] = rotations
    return seeded


@numba.njit(cache=True)
def _nearest_rotations(m: NDArray[np.float64]) -> tuple[NDArray[np.float64], bool]:
    """Orthogonal polar factors of a stack of 3x3 matrices; False when one is singular or a reflection.

    Newton's iteration X <- (X + X^-T) / 2, with X^-T = cofactor(X) / det(X): converges
    quadratically to the nearest rotation for a matrix of positive determinant, and on 10,000
    matrices is far cheaper than a batched SVD.
    """
    out = np.empty_like(m)
    x = np.empty((3, 3))
    cof = np.empty((3, 3))
    for n in range(len(m)):
        x[:] = m[n]
        for _ in range(50):
            for c in range(3):  # column c of the cofactor matrix: cross product of the other two columns
                a, b = (c + 1) % 3, (c + 2) % 3
                cof[0, c] = x[1, a] * x[2, b] - x[2, a] * x[1, b]
                cof[1, c] = x[2, a] * x[0, b] - x[0, a] * x[2, b]
                cof[2, c] = x[0, a] * x[1, b] - x[1, a] * x[0, b]
            det = x[0, 0] * cof[0, 0] + x[1, 0] * cof[1, 0] + x[2, 0] * cof[2, 0]
            if not det > 1e-300:
                return out, False
            change = 0.0
            for i in range(3):
                for j in range(3):
                    value = 0.5 * (x[i, j] + cof[i, j] / det)
                    change = max(change, abs(value - x[i, j]))
                    x[i, j] = value
            if change < 1e-14:
                break
        out[n] = x
    return out, True


def _normal_blocks(
    e: _Edges, rij: NDArray, tij: NDArray, er: NDArray, err: NDArray, count: int
) -> tuple[NDArray, NDArray, NDArray]:
    """Per-node diagonal blocks, per-edge off-diagonal blocks H_ij and per-node gradient, all edges at once."""
    return _accumulate_normal_blocks(e.i, e.j, rij, tij, _inverse_right_jacobian(er), err, e.info, count)


@numba.njit(cache=True)
def _accumulate_normal_blocks(
    ei: NDArray[np.int64],
    ej: NDArray[np.int64],
    rij: NDArray[np.float64],
    tij: NDArray[np.float64],
    jr_inv: NDArray[np.float64],
    err: NDArray[np.float64],
    info: NDArray[np.float64],
    count: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """A_i^T Ω A_i, A_j^T Ω A_j, A_i^T Ω A_j and A^T Ω e of every edge, summed per pose in one pass.

    The Jacobians are A_i = [[-I, [t_ij]x], [0, -J_r^-1 R_ij^T]] and A_j = [[R_ij, 0], [0, J_r^-1]];
    one compiled loop avoids the (edges, 6, 6) temporaries and the slow unbuffered scatter that
    the array version needed, which together cost as much as the sparse factorisation.
    """
    diag = np.zeros((count, 6, 6))
    off = np.zeros((len(ei), 6, 6))
    gradient = np.zeros((count, 6))
    ai = np.zeros((6, 6))
    aj = np.zeros((6, 6))
    wi = np.empty((6, 6))
    wj = np.empty((6, 6))
    for m in range(len(ei)):
        t, r, jr = tij[m], rij[m], jr_inv[m]
        for a in range(3):
            ai[a, a] = -1.0
            for b in range(3):
                aj[a, b] = r[a, b]
                aj[3 + a, 3 + b] = jr[a, b]
                s = 0.0
                for k in range(3):
                    s -= jr[a, k] * r[b, k]
                ai[3 + a, 3 + b] = s
        ai[0, 4], ai[0, 5] = -t[2], t[1]
        ai[1, 3], ai[1, 5] = t[2], -t[0]
        ai[2, 3], ai[2, 4] = -t[1], t[0]
        omega = info[m]
        # W = A^T Ω, skipping the zero blocks: A_i = [[-I, S], [0, B]] and A_j = [[R, 0], [0, J]]
        for a in range(3):
            for b in range(6):
                si = 0.0
                sj = 0.0
                sr = 0.0
                for k in range(3):
                    si += ai[k, 3 + a] * omega[k, b] + ai[3 + k, 3 + a] * omega[3 + k, b]
                    sj += aj[k, a] * omega[k, b]
                    sr += aj[3 + k, 3 + a] * omega[3 + k, b]
                wi[a, b] = -omega[a, b]
                wi[3 + a, b] = si
                wj[a, b] = sj
                wj[3 + a, b] = sr
        i, j = ei[m], ej[m]
        for a in range(6):
            gi = 0.0
            gj = 0.0
            for k in range(6):
                gi += wi[a, k] * err[m, k]
                gj += wj[a, k] * err[m, k]
            gradient[i, a] += gi
            gradient[j, a] += gj
            for b in range(3):  # W A, again over the non-zero blocks of A only
                sii = 0.0
                sjj = 0.0
                sjr = 0.0
                sij = 0.0
                sir = 0.0
                for k in range(3):
                    sii += wi[a, k] * ai[k, 3 + b] + wi[a, 3 + k] * ai[3 + k, 3 + b]
                    sjj += wj[a, k] * aj[k, b]
                    sjr += wj[a, 3 + k] * aj[3 + k, 3 + b]
                    sij += wi[a, k] * aj[k, b]
                    sir += wi[a, 3 + k] * aj[3 + k, 3 + b]
                diag[i, a, b] -= wi[a, b]
                diag[i, a, 3 + b] += sii
                diag[j, a, b] += sjj
                diag[j, a, 3 + b] += sjr
                off[m, a, b] = sij
                off[m, a, 3 + b] = sir
    return diag, off, gradient


def _moved(rot: NDArray, trans: NDArray, step: NDArray, free: NDArray[np.bool_]) -> tuple[NDArray, NDArray]:
    new_rot, new_trans = rot.copy(), trans.copy()
    new_trans[free] += np.einsum("nij,nj->ni", rot[free], step[free, :3])
    new_rot[free] = rot[free] @ so3_exp(step[free, 3:])
    return new_rot, new_trans


def relative_pose(pose_i: Matrix, pose_j: Matrix) -> Matrix:
    """The measurement an edge i->j holds for given world poses: scan j in scan i's frame."""
    return invert(pose_i) @ pose_j


def point_pair_information(data_in_i: NDArray[np.float64], origin_j_in_i: Matrix, sigma2: float) -> Matrix:
    """Information (inverse covariance) of an ICP result from its point pairs, as in LUM.

    Linearising the point-to-point error of the pairs around the match gives the Gauss-Newton
    Hessian ``sum J^T J / σ²`` with, per data point p (in scan i's frame), J = [I, -[p - t_ij]x R_ij];
    σ² is the mean squared pair distance. A long flat corridor thus gets little information along
    its axis, which is what lets the relaxation move scans where the geometry does not hold them.
    """
    rij = origin_j_in_i[:3, :3]
    q = data_in_i - origin_j_in_i[:3, 3]
    n = q.shape[0]
    if n == 0:
        return np.zeros((6, 6))
    # J_r = -[q]x R_ij ; H = [[n I, sum J_r], [sum J_r^T, sum J_r^T J_r]]
    sq = skew(q)
    jr = -sq @ rij
    info = np.zeros((6, 6))
    info[:3, :3] = n * np.eye(3)
    s = jr.sum(axis=0)
    info[:3, 3:] = s
    info[3:, :3] = s.T
    info[3:, 3:] = np.einsum("nki,nkj->ij", jr, jr)
    return info / max(sigma2, 1e-12)
