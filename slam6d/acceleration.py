"""Anderson acceleration of a fixed-point iteration, and the chart that lets poses take part in it.

LUM's rounds are a fixed-point iteration: pair the points at the current poses, solve, move. On a
long loop whose steps registration left a little short, each round removes only about half of
what is left of that low-frequency error (the dense simulated loop at 400 scans: 25.4, 15.1, 8.0,
3.8, 1.7, 0.8 cm ATE at the starts of its rounds), so the rounds needed grow with how far off the
relaxation starts. The contraction is steady from round to round, which is what Anderson's mixing
(Walker & Ni, "Anderson acceleration for fixed-point iterations", 2011; used for ICP by Pavlov et
al., "AA-ICP", 2018) exploits: the next iterate is the combination of the last few rounds' results
whose residual (result minus start) is least, in effect a secant step along the slow modes.

The mixing is linear, so the poses go through :class:`PoseChart`: each pose as the 6-vector of its
offset from a fixed origin pose (translation and rotation vector in the origin's frame), the same
chart for every round of one relaxation.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from slam6d.geometry import Matrix, make_pose, so3_exp, so3_log

FloatArray = NDArray[np.float64]

__all__ = ["AndersonMixer", "PoseChart"]


class PoseChart:
    """Poses as (n, 6) vectors [ρ, φ] about fixed origins X0: X = X0 · [Exp(φ), ρ].

    Smooth and one-to-one for rotations under pi away from the origin; a relaxation moves its
    scans by a few degrees at most, so a round's results and their combinations stay well inside it.
    """

    def __init__(self, origins: Sequence[Matrix]) -> None:
        self.origins = np.array(origins, dtype=np.float64)
        self._inverse_rotations = np.transpose(self.origins[:, :3, :3], (0, 2, 1))

    def vectors(self, poses: Sequence[Matrix] | FloatArray, which: NDArray[np.int64] | None = None) -> FloatArray:
        """The chart's (n, 6) coordinates of ``poses``, one per origin (or per origin of ``which``)."""
        stacked = np.asarray(poses, dtype=np.float64)
        origins = self.origins if which is None else self.origins[which]
        inverse = self._inverse_rotations if which is None else self._inverse_rotations[which]
        rho = np.einsum("nij,nj->ni", inverse, stacked[:, :3, 3] - origins[:, :3, 3])
        phi = so3_log(inverse @ stacked[:, :3, :3])
        return np.concatenate([rho, phi], axis=1)

    def poses(self, vectors: FloatArray, which: NDArray[np.int64] | None = None) -> FloatArray:
        """The (n, 4, 4) poses of chart coordinates (about the origins of ``which``, if given): the
        inverse of :meth:`vectors`."""
        origins = self.origins if which is None else self.origins[which]
        return origins @ make_pose(so3_exp(vectors[:, 3:]), vectors[:, :3])


class AndersonMixer:
    """Anderson's mixing (type II) of depth ``depth`` for the iteration y -> g(y).

    :meth:`mix` takes an iterate y_k and its image g_k = g(y_k) and returns the next iterate:
    g_k minus the combination of the last ``depth`` differences of the images whose matching
    combination of residual differences best cancels f_k = g_k - y_k (least squares, each
    coordinate weighted by ``metric``). With no history it returns g_k itself, the plain iteration.
    The coefficients are bounded by ``max_coefficient``: a history whose residual differences are
    nearly parallel (a stalled iteration) would otherwise ask for an arbitrarily long step.
    """

    def __init__(self, depth: int, metric: FloatArray | None = None, max_coefficient: float = 10.0) -> None:
        if depth < 1:
            raise ValueError(f"an Anderson mixer needs a depth of at least 1, got {depth}")
        self.depth = depth
        self.metric = metric
        self.max_coefficient = max_coefficient
        self._history: deque[tuple[FloatArray, FloatArray]] = deque(maxlen=depth + 1)  # (g, f) per iterate

    def reset(self) -> None:
        """Forget the history: the iteration's map changed (another sample, another robust scale)."""
        self._history.clear()

    def mix(self, iterate: FloatArray, image: FloatArray) -> FloatArray:
        """The next iterate after ``iterate`` whose plain successor is ``image`` (both any shape)."""
        g = np.asarray(image, dtype=np.float64).ravel()
        f = g - np.asarray(iterate, dtype=np.float64).ravel()
        f_weighted = f * self.metric.ravel() if self.metric is not None else f
        self._history.append((g, f_weighted))
        if len(self._history) < 2:
            return g.reshape(np.shape(image))
        images = np.array([h[0] for h in self._history])
        residuals = np.array([h[1] for h in self._history])
        d_images = np.diff(images, axis=0)
        d_residuals = np.diff(residuals, axis=0)
        gamma, *_ = np.linalg.lstsq(d_residuals.T, f_weighted, rcond=1e-10)
        if not np.all(np.isfinite(gamma)) or np.abs(gamma).max() > self.max_coefficient:
            self.reset()
            self._history.append((g, f_weighted))
            return g.reshape(np.shape(image))
        return (g - gamma @ d_images).reshape(np.shape(image))
