"""Sparse least-squares pose graph: the linear algebra behind LUM-style global relaxation.

Each edge says "scan j sits at ``measurement`` in scan i's frame, with this 6x6 information". The
solver minimises ``sum e^T Ω e`` over all poses with Gauss-Newton (Levenberg damping only when a
step would increase the error), building the Jacobians for every edge at once with numpy and
solving the sparse normal equations with SuperLU. That keeps a 10,000-pose graph well inside a
second without a compiled graph library.

Error of an edge, with poses X = (R, t):
    e_t = R_i^T (t_j - t_i) - t_z          (translation, in scan i's frame)
    e_r = Log(R_z^T R_i^T R_j)             (rotation, right-perturbation of scan j)
and the update R <- R Exp(φ), t <- t + R ρ. The Jacobians below are exact (including the inverse
right Jacobian of SO(3)), so the converged poses are the true least-squares optimum.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix, invert, make_pose


class RelaxationError(Slam6dError):
    """Global relaxation cannot run or did not produce a usable result; the message says why."""


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


# ---------------------------------------------------------------- vectorised SO(3)


def _skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rodrigues' formula for a stack of rotation vectors (..., 3) -> (..., 3, 3)."""
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    k = _skew(phi)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def so3_log(rotation: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vectors of a stack of rotations (..., 3, 3) -> (..., 3), stable near 0 and near pi."""
    cos = np.clip((np.trace(rotation, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    vee = np.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        axis=-1,
    )
    small = theta < 1e-6
    sin = np.sin(theta)
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    out = vee * scale[..., None]
    near_pi = theta > np.pi - 1e-3
    if np.any(near_pi):  # the antisymmetric part vanishes there: read the axis off the symmetric part
        for index in np.argwhere(near_pi.reshape(-1)).ravel():
            r = rotation.reshape(-1, 3, 3)[index]
            th = theta.reshape(-1)[index]
            col = int(np.argmax(np.diag(r)))
            axis = (r[:, col] + np.eye(3)[col]) / np.sqrt(max(2.0 * (1.0 + r[col, col]), 1e-300))
            vec = axis * th
            if np.dot(vec, vee.reshape(-1, 3)[index]) < 0.0:
                vec = -vec
            out.reshape(-1, 3)[index] = vec
    return out


def _inverse_right_jacobian(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    k = _skew(phi)
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
    meas = np.stack([np.asarray(e.measurement, dtype=np.float64) for e in edges])
    info = np.stack([np.asarray(e.information, dtype=np.float64) for e in edges])
    if not (np.isfinite(meas).all() and np.isfinite(info).all()):
        raise RelaxationError("an edge has a non-finite measurement or information matrix")
    info = 0.5 * (info + np.transpose(info, (0, 2, 1)))
    return _Edges(i, j, meas[:, :3, :3], meas[:, :3, 3], info)


def check_connected(count: int, edge_pairs: Iterable[tuple[int, int]], fixed: Iterable[int]) -> None:
    """Every pose must be tied to a fixed pose through edges, or its position is undetermined."""
    pairs = np.array(list(edge_pairs), dtype=np.int64).reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    _, labels = csgraph.connected_components(graph, directed=False)
    anchored = {int(labels[f]) for f in fixed}
    loose = [k for k in range(count) if int(labels[k]) not in anchored]
    if loose:
        shown = ", ".join(str(k) for k in loose[:12]) + (" ..." if len(loose) > 12 else "")
        raise RelaxationError(
            f"the pose graph is disconnected: {len(loose)} scan(s) ({shown}) share no edge path with a fixed scan; "
            "they do not overlap the rest enough (more point pairs, a larger max distance or odometry edges needed)"
        )


def _errors(rot: NDArray, trans: NDArray, e: _Edges) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    ri, rj = rot[e.i], rot[e.j]
    rij = np.einsum("mki,mkj->mij", ri, rj)
    tij = np.einsum("mki,mk->mi", ri, trans[e.j] - trans[e.i])
    et = tij - e.tz
    er = so3_log(np.einsum("mki,mkj->mij", e.rz, rij))
    return np.concatenate([et, er], axis=1), rij, tij, er


def _chi2(err: NDArray, info: NDArray) -> float:
    return float(np.einsum("mi,mij,mj->", err, info, err))


def optimize_pose_graph(
    poses: Sequence[Matrix],
    edges: Sequence[PoseEdge],
    fixed: Iterable[int] = (0,),
    max_iterations: int = 30,
    tolerance: float = 1e-10,
    progress: Callable[[int, float], None] | None = None,
) -> PoseGraphResult:
    """Least-squares poses for a graph of relative measurements; ``fixed`` poses do not move.

    Raises :class:`RelaxationError` on a disconnected graph, on non-finite input, or when the
    normal equations are singular (a pose constrained in fewer than 6 degrees of freedom).
    """
    count = len(poses)
    fixed_set = {int(f) for f in fixed}
    if not fixed_set:
        raise RelaxationError("no fixed pose: the graph's absolute position would be undetermined (fix scan 0)")
    if any(f < 0 or f >= count for f in fixed_set):
        raise RelaxationError(f"fixed pose index out of range for {count} poses: {sorted(fixed_set)}")
    packed = _pack_edges(edges, count)
    check_connected(count, zip(packed.i.tolist(), packed.j.tolist(), strict=True), fixed_set)

    stack = np.stack([np.asarray(p, dtype=np.float64) for p in poses])
    rot, trans = stack[:, :3, :3].copy(), stack[:, :3, 3].copy()

    var = -np.ones(count, dtype=np.int64)
    free = np.array([k for k in range(count) if k not in fixed_set], dtype=np.int64)
    var[free] = np.arange(len(free))
    size = 6 * len(free)

    # Sparsity pattern is the same every iteration: precompute COO indices of the four blocks per edge.
    block = np.arange(6)
    rows_b, cols_b = np.meshgrid(block, block, indexing="ij")
    pattern = []
    for a, b in (("i", "i"), ("i", "j"), ("j", "i"), ("j", "j")):
        va, vb = var[getattr(packed, a)], var[getattr(packed, b)]
        keep = (va >= 0) & (vb >= 0)
        rows = (6 * va[:, None, None] + rows_b)[keep].ravel()
        cols = (6 * vb[:, None, None] + cols_b)[keep].ravel()
        pattern.append((keep, rows, cols))

    err, rij, tij, er = _errors(rot, trans, packed)
    chi2 = _chi2(err, packed.info)
    before = chi2
    damping = 0.0
    converged = False
    iteration = 0
    if size == 0:
        converged = True
    for iteration in range(1, max_iterations + 1):
        if size == 0:
            break
        m = len(packed.i)
        ai = np.zeros((m, 6, 6))
        aj = np.zeros((m, 6, 6))
        jr_inv = _inverse_right_jacobian(er)
        ai[:, :3, :3] = -np.eye(3)
        ai[:, :3, 3:] = _skew(tij)
        ai[:, 3:, 3:] = -jr_inv @ np.transpose(rij, (0, 2, 1))
        aj[:, :3, :3] = rij
        aj[:, 3:, 3:] = jr_inv
        wi = np.einsum("mki,mkl->mil", ai, packed.info)  # A_i^T Ω
        wj = np.einsum("mki,mkl->mil", aj, packed.info)
        blocks = {"ii": wi @ ai, "ij": wi @ aj, "ji": wj @ ai, "jj": wj @ aj}
        data = []
        rows = []
        cols = []
        for (keep, r, c), key in zip(pattern, ("ii", "ij", "ji", "jj"), strict=True):
            data.append(blocks[key][keep].ravel())
            rows.append(r)
            cols.append(c)
        hessian = sp.csc_matrix(
            (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size)
        )
        gradient = np.zeros(size)
        gi = np.einsum("mij,mj->mi", wi, err)
        gj = np.einsum("mij,mj->mi", wj, err)
        for v, g in ((var[packed.i], gi), (var[packed.j], gj)):
            keep = v >= 0
            np.add.at(gradient, (6 * v[keep][:, None] + block).ravel(), g[keep].ravel())

        while True:
            system = hessian if damping == 0.0 else hessian + damping * sp.diags(hessian.diagonal() + 1e-9)
            try:
                # The system is symmetric positive definite: a symmetric fill-reducing ordering with
                # diagonal pivots is several times faster than SuperLU's general-matrix default.
                factor = spla.splu(
                    system.tocsc(),
                    permc_spec="MMD_AT_PLUS_A",
                    diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True},
                )
                pivots = np.abs(factor.U.diagonal())
                if pivots.min() <= 1e-12 * pivots.max():
                    raise RuntimeError("a pivot vanished")
                step = factor.solve(-gradient)
            except RuntimeError as exc:
                raise RelaxationError(
                    f"the pose-graph normal equations are singular ({exc}); some scan is constrained in fewer "
                    "than 6 degrees of freedom (degenerate information matrices)"
                ) from exc
            if not np.isfinite(step).all():
                raise RelaxationError("the pose-graph solver produced a non-finite step (ill-conditioned graph)")
            delta = step.reshape(-1, 6)
            new_rot, new_trans = rot.copy(), trans.copy()
            new_trans[free] += np.einsum("nij,nj->ni", rot[free], delta[:, :3])
            new_rot[free] = rot[free] @ so3_exp(delta[:, 3:])
            new_err, new_rij, new_tij, new_er = _errors(new_rot, new_trans, packed)
            new_chi2 = _chi2(new_err, packed.info)
            if new_chi2 <= chi2 * (1.0 + 1e-12) or damping > 1e8:
                break
            damping = 1e-4 if damping == 0.0 else damping * 10.0
        improvement = chi2 - new_chi2
        rot, trans, err, rij, tij, er, chi2 = new_rot, new_trans, new_err, new_rij, new_tij, new_er, new_chi2
        damping = damping / 10.0 if damping > 1e-6 else 0.0
        if progress is not None:
            progress(iteration, chi2)
        if improvement <= tolerance * max(before, 1e-300) or float(np.abs(step).max()) < 1e-10:
            converged = True
            break
    result_poses = [make_pose(rot[k], trans[k]) for k in range(count)]
    return PoseGraphResult(
        poses=result_poses,
        residual_before=before,
        residual_after=chi2,
        iterations=iteration,
        converged=converged,
        edge_translation_error=np.linalg.norm(err[:, :3], axis=1).tolist(),
        edge_rotation_error=np.linalg.norm(err[:, 3:], axis=1).tolist(),
    )


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
    sq = _skew(q)
    jr = -sq @ rij
    info = np.zeros((6, 6))
    info[:3, :3] = n * np.eye(3)
    s = jr.sum(axis=0)
    info[:3, 3:] = s
    info[3:, :3] = s.T
    info[3:, 3:] = np.einsum("nki,nkj->ij", jr, jr)
    return info / max(sigma2, 1e-12)
