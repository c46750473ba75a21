"""The measured tilt: an inclinometer's (or an IMU's gravity vector's) "up" in each scanner's frame.

Registration measures roll and pitch only relative to the scans before, so its errors accumulate:
on the simulated campus a car's VLP-16 leaves ICP 0.1° of roll/pitch error per 3 m step even
against three fused scans (docs/scale.md, "The rings' own planes"), and over the stretches no loop
closes that bends the path up and down by tens of centimetres. An inclinometer measures the
direction of gravity in the sensor's frame, absolutely: its error does not grow with the path.
:class:`TiltPrior` holds those measurements as a unary constraint on each scan's attitude, two
degrees of freedom (rotations about "up", the heading, are not measured by gravity):

    residual  e_k = R_kᵀ u - m_k         (u: the world's up, canonical +z; m_k: measured up, scan frame)

with the sensor's stated noise ``noise_deg`` per axis. :func:`tilt_normal_equations` gives its
normal-equation terms for a rotation update on either side, and the sequential ICP
(:func:`slam6d.icp.icp_iterations`), the LUM relaxation (:func:`slam6d.lum.lum_relaxation`) and
the pose graph (:func:`slam6d.posegraph.optimize_pose_graph`) add them; loop closing keeps the
measured tilt by correcting only the heading and the position (:func:`heading_only`).

**How much it weighs.** Both minimise point-to-plane residuals in metres, each point pair with unit
weight: taken at face value the information on a scan's tilt is the sum over thousands of pairs
and a 0.3° inclinometer would weigh nothing beside it. It is not worth that much: the point pairs'
errors are systematic (the rings' normals, the same for every pair on the same surface), and the
tilt of a step is known to ``registration_deg`` (0.1° RMS per step on the campus, matched from the
truth; the pairs' own covariance claims ~0.001°). So the pairs' tilt information, whatever its
absolute scale, is taken to stand for that per-step error, and the prior gets ``(registration_deg
/ noise_deg)²`` times it in a joint solve (:attr:`TiltPrior.ratios`), and the steady-state Kalman
share in a sequential fit, whose model carries the tilt error accumulated so far
(:meth:`TiltPrior.sequential_ratio`): the fit then mixes the registration's tilt and the
inclinometer's as two measurements with those standard deviations would be mixed, a filter whose
error stays bounded instead of accumulating. What a step's tilt is worth depends on the scans:
:data:`RINGS_TILT_DEG` (0.1°) where the pipeline matches against fused scans because a scan's
rings lie too far apart to hold planes (a VLP-16 outdoors), :data:`PLANES_TILT_DEG` (0.006°)
where scans find their planes alone (a dense scanner; weighed at 0.1° there, the reading's noise
pulled the simulated loop from 0.18 to 0.35 cm ATE).

**When it applies.** Only where the roll and pitch of the odometry really are measured: an
inclinometer, an IMU's gravity estimate. Wheel odometry from a 2D robot (Kurt3D's and 3DTK's
``.pose`` files) carries zeros for roll and pitch, and a gyro integrated over time drifts like the
registration does; constraining either to "level" would bend a map of a ramp flat. So it is off
unless the session declares an inclinometer (the simulator writes ``inclinometer`` into
``simulation.json``; :func:`declared_tilt_noise`) or the user states the noise
(``slam6d run --tilt-noise-deg``, ``[engine] tilt_noise_deg`` in a session.toml).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix, rot_z

FloatArray = NDArray[np.float64]

UP = np.array([0.0, 0.0, 1.0])  # the canonical frame's up (slam6d.scan: right-handed, z up)
# What registration's tilt is worth per step (see the module docstring), for the two kinds of
# registration model the pipeline chooses between: scans whose rings lie too far apart to hold
# planes, matched against three fused scans (the campus's VLP-16 from the truth: 0.102° roll /
# 0.085° pitch RMS), and scans that find their planes alone (the simulated dense loop, sequential
# registration: 0.006° per step).
RINGS_TILT_DEG = 0.1
PLANES_TILT_DEG = 0.006
SIMULATION_FILE = "simulation.json"

__all__ = [
    "PLANES_TILT_DEG",
    "RINGS_TILT_DEG",
    "UP",
    "Readings",
    "ScanTilt",
    "TiltPrior",
    "declared_tilt_noise",
    "heading_only",
    "measured_up",
    "measured_ups",
    "tilt_error_deg",
    "tilt_information",
    "tilt_normal_equations",
]


def measured_up(pose: Matrix) -> FloatArray:
    """The world's up in the frame of a scan whose world_from_scan is ``pose``: what an
    inclinometer on it reads (independent of its heading)."""
    return np.asarray(pose, dtype=np.float64)[:3, :3].T @ UP


def measured_ups(rotations: FloatArray) -> FloatArray:
    """:func:`measured_up` of many scans at once from their rotations (n, 3, 3): Rᵀ u is R's last
    row, u being the canonical z."""
    return np.ascontiguousarray(np.asarray(rotations, dtype=np.float64)[..., 2, :])


def tilt_error_deg(pose: Matrix, up: FloatArray) -> float:
    """Angle between the up that ``pose`` implies and the measured ``up``, degrees."""
    cosine = float(np.clip(measured_up(pose) @ (up / np.linalg.norm(up)), -1.0, 1.0))
    return math.degrees(math.acos(cosine))


@dataclass(frozen=True)
class Readings:
    """An inclinometer's readings as the odometry poses that carry them (canonical
    ``world_from_scan``; only their roll and pitch are read) and, per scan, whether it has one (a
    scan whose file carried no pose has none)."""

    poses: list[Matrix]
    measured: list[bool]


@dataclass(frozen=True)
class TiltPrior:
    """Measured up per scan (``ups[k]``, scan frame, unit; rows of scans without a reading are
    unused, ``measured[k]`` False) with the sensor's noise and, per scan, the registration's
    per-step tilt error it is weighed against (``registration_deg``; module docstring). The
    pipeline sets a scan's entry when it chooses the scan's model (:meth:`registered_with`)."""

    ups: FloatArray  # (n, 3)
    measured: NDArray[np.bool_]  # (n,)
    noise_deg: float
    registration_deg: FloatArray  # (n,)

    def __post_init__(self) -> None:
        if not (self.noise_deg > 0 and math.isfinite(self.noise_deg)):
            raise ValueError(f"the inclinometer's noise must be a positive number of degrees, got {self.noise_deg}")
        if self.ups.shape != (len(self.measured), 3) or self.registration_deg.shape != (len(self.measured),):
            raise ValueError(
                f"ups must be (n, 3) and registration_deg (n,) beside n measured flags, got {self.ups.shape}"
                f" and {self.registration_deg.shape} for {len(self.measured)}"
            )
        self._check_registration(self.registration_deg)

    @staticmethod
    def _check_registration(degrees: FloatArray | float) -> None:
        if not np.all((np.asarray(degrees) > 0) & np.isfinite(degrees)):
            raise ValueError(f"the registration's tilt per step must be a positive number of degrees, got {degrees}")

    @classmethod
    def from_poses(
        cls,
        poses: Sequence[Matrix],
        measured: Sequence[bool],
        noise_deg: float,
        registration_deg: float = PLANES_TILT_DEG,
    ) -> TiltPrior:
        """The readings carried by odometry poses (their roll and pitch; their heading and position
        are ignored); ``measured[k]`` False for scans without odometry. Every scan's registration
        is taken to be worth ``registration_deg`` until :meth:`registered_with` says otherwise."""
        ups = np.array([measured_up(p) for p in poses]).reshape(len(poses), 3)
        registration = np.full(len(poses), float(registration_deg))
        return cls(ups, np.array(measured, dtype=bool), float(noise_deg), registration)

    def registered_with(self, index: int, registration_deg: float) -> None:
        """Scan ``index`` was registered by a model whose tilt is worth ``registration_deg`` per step."""
        self._check_registration(registration_deg)
        self.registration_deg[index] = registration_deg

    @property
    def ratios(self) -> FloatArray:
        """Per scan, the prior's weight as a share of one step's tilt information in a joint solve
        (LUM, a pose graph), where the steps relate the scans to each other and every scan has its
        own reading: (registration / noise)²."""
        return np.asarray((self.registration_deg / self.noise_deg) ** 2, dtype=np.float64)

    def sequential_ratio(self, index: int) -> float:
        """The prior's weight as a share of scan ``index``'s sequential fit's tilt information.
        There the model is the scans registered before, whose tilt is itself only known to the
        filter's steady state P (a Kalman filter over the steps: predict P + q, q = registration²,
        update with the reading, r = noise²), so the fit's tilt is worth P + q, not q, and the
        reading gets (P + q) / r with P + q = (q + sqrt(q² + 4 q r)) / 2: 0.39 for 0.1° against
        0.3° where q / r would give 0.11. With q / r a per-step bias b of the registration settled
        at 9 b off the reading (a first-order filter's a b / (1 - a), a = 0.9): 0.58° on the
        campus's ramp."""
        q, r = float(self.registration_deg[index]) ** 2, self.noise_deg**2
        return (q + math.sqrt(q * q + 4.0 * q * r)) / 2.0 / r

    def __len__(self) -> int:
        return len(self.measured)

    def weights(self, step_information: Sequence[float] | FloatArray) -> FloatArray:
        """Per scan, the prior's weight in a joint solve: :attr:`ratios` x the median tilt
        information the registration's steps hold there (:func:`tilt_information`; all 0 when
        none has any, which leaves the prior out)."""
        information = np.asarray(step_information, dtype=np.float64).ravel()
        positive = information[information > 0]
        return self.ratios * (float(np.median(positive)) if len(positive) else 0.0)

    def terms(
        self, rotations: FloatArray, free: NDArray[np.bool_], weights: FloatArray
    ) -> tuple[FloatArray, FloatArray, float]:
        """For a joint solve with right perturbations R <- R Exp(φ): per scan the block to add to
        the rotation part of its normal equations, the gradient to add (the normal equations solve
        A δ = -gradient), both zero for scans held or without a reading, and the prior's χ²."""
        count = len(rotations)
        if count != len(self):
            raise ValueError(f"the tilt prior has readings for {len(self)} scans, the solve has {count}")
        blocks, gradient = np.zeros((count, 3, 3)), np.zeros((count, 3))
        active = np.flatnonzero(free & self.measured & (weights > 0))
        implied = np.einsum("kji,j->ki", np.asarray(rotations, dtype=np.float64)[active], UP)  # R_kᵀ u
        blocks[active], gradient[active] = tilt_normal_equations(implied, self.ups[active], weights[active])
        chi2 = float(np.sum(weights[active] * np.sum((implied - self.ups[active]) ** 2, axis=1)))
        return blocks, gradient, chi2

    def for_fit(self, index: int, world_from_model: Matrix) -> ScanTilt | None:
        """Scan ``index``'s reading for a fit against a model placed at ``world_from_model``; None
        when the scan has none."""
        if not self.measured[index]:
            return None
        return ScanTilt(self.ups[index], np.asarray(world_from_model)[:3, :3].T @ UP, self.sequential_ratio(index))


def tilt_information(hessian: FloatArray, up: FloatArray) -> FloatArray:
    """The mean information a 6x6 point-to-plane system (rotation first, then translation; any
    common scale) holds on the two tilt axes perpendicular to ``up``, with the translation free
    (the Schur complement: a tilt about the scanner that a shift undoes is no information).

    One system (6, 6) with its ``up`` (3,) gives one number, a stack (n, 6, 6) with (n, 3) one
    each: a joint solve weighs every scan's prior each round, and one call per scan (3,200 over the
    rounds of a 400-scan relaxation) cost 0.15 s of CPU, 0.65 s under cProfile; ICP calls it with
    one system per iteration. A translation block that cannot be inverted (a scan without pairs)
    leaves the rotation block as it is.
    """
    hessian = np.asarray(hessian, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    reduced = _rotation_with_translation_free(hessian[..., :3, :3], hessian[..., :3, 3:], hessian[..., 3:, 3:])
    across = np.eye(3) - up[..., :, None] * up[..., None, :]
    return np.maximum(np.trace(across @ reduced @ across, axis1=-2, axis2=-1) / 2.0, 0.0)


def _rotation_with_translation_free(rotation: FloatArray, mixed: FloatArray, translation: FloatArray) -> FloatArray:
    """rotation - mixed inv(translation) mixedᵀ, per system; the rotation block itself where the
    translation block is singular (solved one by one only then: a stack that holds one)."""
    try:
        return rotation - mixed @ np.linalg.solve(translation, np.swapaxes(mixed, -1, -2))
    except np.linalg.LinAlgError:
        if translation.ndim == 2:
            return rotation
        return np.array(
            [_rotation_with_translation_free(*system) for system in zip(rotation, mixed, translation, strict=True)]
        )


def tilt_normal_equations(
    turned: FloatArray, target: FloatArray, weight: float | FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(A, b) to add to the normal equations A ω = b of a rotation update ω that turns the unit
    vector ``turned`` to ``turned + ω × turned``, for the residual ``turned - target`` with weight w:
    A = w (I - t tᵀ) (the two axes across it; a turn about itself changes nothing), b = w (t × target).
    For many at once (a joint solve's scans, one call instead of one per scan: 18,000 calls cost
    ~2 s of a 400-scan run), ``turned`` and ``target`` are (n, 3) and ``weight`` (n,); one vector gives the same bits either way.

    * ICP (update on the left, model frame, T <- Exp(ω) T): ``turned`` is the measured up carried
      into the model frame by the current transform, ``target`` the world's up in the model frame.
    * LUM (update on the right, X <- X Exp(φ)): the implied up ``R_kᵀ u`` is turned by -φ, so pass
      it as ``turned`` with the reading as ``target`` and negate b.
    """
    t = turned / np.linalg.norm(turned, axis=-1, keepdims=True)
    w = np.asarray(weight, dtype=np.float64)
    return w[..., None, None] * (np.eye(3) - t[..., :, None] * t[..., None, :]), w[..., None] * np.cross(t, target)


def heading_only(correction: Matrix, kept: FloatArray) -> Matrix:
    """A world-frame correction (applied on the left) reduced to its turn about the world's up,
    with its translation changed so that the point ``kept`` (the corrected scan's position) still
    lands where the full correction puts it.

    What loop closing applies where the scans' tilt is measured: a verified loop's relative roll
    and pitch are a registration's (0.1-0.5° off on the campus's revisits), and its correction
    turns every scan after the loop by it (``slam6d.loops.diffuse_loop_correction``), which on the
    1,000-scan campus tilted the last 140 scans by 0.3-0.5° away from the inclinometer-held
    registration and raised them 1.5 m. The heading and the position of the loop's end are kept;
    the tilt stays the inclinometer's (module docstring).
    """
    correction = np.asarray(correction, dtype=np.float64)
    rotation = correction[:3, :3]
    yaw = math.atan2(rotation[1, 0] - rotation[0, 1], rotation[0, 0] + rotation[1, 1])
    level = rot_z(yaw)
    kept = np.asarray(kept, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = level
    out[:3, 3] = rotation @ kept + correction[:3, 3] - level @ kept
    return out


def declared_tilt_noise(source: Path | str) -> float | None:
    """The inclinometer noise (degrees) a scan folder declares, or None: the simulator's
    ``simulation.json`` names the ``inclinometer`` its odometry poses carry (``{"roll_pitch_noise_deg":
    0.3}``). Sessions simulated before it said so declare it through their settings (odometry written
    and ``odometry_tilt_noise_deg`` > 0: the simulator's odometry always carried the reading).
    Anything else (no such file, another generator, no odometry) declares nothing."""
    path = Path(source)
    path = path / SIMULATION_FILE if path.is_dir() else path.parent / SIMULATION_FILE
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise Slam6dError(f"{path}: not readable as JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("generator") != "slam6d simulate":
        return None
    declared = meta.get("inclinometer")
    if isinstance(declared, dict):
        value = declared.get("roll_pitch_noise_deg")
        if not isinstance(value, int | float) or not value > 0:
            raise Slam6dError(f"{path}: inclinometer.roll_pitch_noise_deg must be a positive number, got {value!r}")
        return float(value)
    config = meta.get("config")
    if declared is None and isinstance(config, dict) and config.get("odometry"):
        value = config.get("odometry_tilt_noise_deg")
        if isinstance(value, int | float) and value > 0:
            return float(value)
    return None


@dataclass(frozen=True)
class ScanTilt:
    """One scan's reading for a pairwise fit (:func:`slam6d.icp.icp_iterations`): the measured up
    in the data scan's own frame, the world's up in the model's frame, and the prior's share of
    the pairs' tilt information (:attr:`TiltPrior.sequential_ratio`)."""

    reading: FloatArray
    up: FloatArray
    ratio: float
