"""Working on a session's stored revision again: ``slam6d relax`` and the workbench's Relax, Close loops and runs.

A revision is relaxed without the run that made it, so what that run knew besides the scans has to
be found again in the session: its graph (the sequential links and the edges of
:mod:`slam6d.session_graph`) and, where the session declares an inclinometer (``[engine]
tilt_noise_deg``, which :meth:`slam6d.session.Session.create` writes for a folder that declares
one), the readings. Those are the odometry's roll and pitch: revision 0 of the journal, the poses
the scan files carried (written when the session was first opened), for the scans whose file
carried a pose (:func:`session_readings`). Relaxing without them lets the scan pairs' systematic
relative tilt (0.1° per step between a VLP-16's rings) bend the map up and down again where
registration had held it to the readings. Here each door gets what ``slam6d run`` does with them:

* :func:`relax_revision` with :func:`revision_tilt_prior` (``slam6d relax``, the workbench's
  *Relax*): the same readings weighed by the same rule as the run's relaxation stage
  (:func:`slam6d.pipeline.registration_tilt_deg`), and ``lum`` paired against the same scan models
  (:func:`slam6d.pipeline.share_registration_models`);
* :func:`close_revision_loops` (the workbench's *Close loops*): corrections that keep the tilt
  (:func:`slam6d.attitude.heading_only`), as the run's loop closing;
* :func:`registration_readings` (the workbench's registration runs, which start from the head):
  revision 0's readings, not the head's estimate.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from slam6d.attitude import Readings, TiltPrior, heading_only
from slam6d.errors import Cancelled, InvalidValueError, SessionError
from slam6d.geometry import Matrix, check_rigid
from slam6d.journal import Revision
from slam6d.loops import LoopHypothesis, diffuse_loop_correction, loop_correction
from slam6d.pipeline import (
    PipelineConfig,
    fuses_scans,
    holds_inclinometer,
    inclinometer_prior,
    needs_fusing,
    registration_model,
    registration_tilt_deg,
    share_registration_models,
)
from slam6d.relax import Progress, RelaxationResult, ScanModels
from slam6d.relaxation_methods import relax_poses
from slam6d.session import JOURNAL_FILE, SESSION_FILE, Session
from slam6d.session_graph import graph_edges, sequential_links

if TYPE_CHECKING:
    from slam6d.scheduler import Scheduler

__all__ = ["close_revision_loops", "registration_readings", "relax_revision", "revision_tilt_prior", "session_readings"]


def session_readings(session: Session, measured: Sequence[bool]) -> Readings:
    """The inclinometer's readings of ``session``: revision 0's poses for the scans whose file
    carried a pose (``measured``, e.g. ``Scan.has_pose`` of its loaded scans).

    :class:`~slam6d.errors.SessionError` naming the journal (or ``session.toml``'s sources) when
    there are none, they do not cover the scans, or a reading is not a rotation."""
    journal = session.folder / JOURNAL_FILE
    first = session.journal.revision(0)
    if first is None:
        raise SessionError(
            journal, "has no revision 0 (the odometry poses the scan files carried) to read the tilt from"
        )
    if len(first.poses) != len(measured):
        raise SessionError(
            journal, f"revision 0 holds {len(first.poses)} odometry poses but the session has {len(measured)} scans"
        )
    if not any(measured):
        raise SessionError(
            session.folder / SESSION_FILE,
            "[engine] tilt_noise_deg (or --tilt-noise-deg) needs the odometry's roll and pitch, but no scan of"
            " [source] paths carried a pose",
        )
    poses = []
    for k, pose in enumerate(first.poses):
        try:
            poses.append(check_rigid(pose, f"revision 0, poses[{k}]") if measured[k] else np.asarray(pose))
        except InvalidValueError as exc:  # a journal edited by hand: stored poses are checked on writing
            raise SessionError(journal, f"the odometry of {exc}") from None
    return Readings(poses, [bool(m) for m in measured])


def registration_readings(session: Session, config: PipelineConfig, measured: Sequence[bool]) -> Readings | None:
    """The readings a registration of ``session`` holds (``Pipeline(readings=...)``): revision 0's
    where ``config`` declares an inclinometer and some scan carried a pose, else None (nothing to
    hold). A workbench run starts from the session's head, whose poses are an earlier run's
    estimate: taken for the readings, they would hold every scan to the tilt that run reached."""
    if not holds_inclinometer(config, measured):
        return None
    return session_readings(session, measured)


def revision_tilt_prior(
    config: PipelineConfig, method: str, readings: Callable[[], Readings], models: ScanModels
) -> TiltPrior | None:
    """The inclinometer prior for relaxing one of a session's revisions by ``method``, or None
    without one (``config.tilt_noise_deg`` unset) or for ``simultaneous``, which ``slam6d run``
    relaxes without it too. ``readings`` is only called when the prior applies.

    Each scan's reading is weighed against what its registration's tilt is worth per step, decided
    as sequential registration decides it (:func:`slam6d.pipeline.fuses_scans` on the scans'
    registration models, built here from ``models``): 0.1° for a VLP-16 outdoors, 0.006° for a
    scan that finds its planes alone; a relaxed run's own prior carries the same weights.
    """
    if config.tilt_noise_deg is None or method == "simultaneous":
        return None
    found = readings()
    if len(found.poses) != len(models):
        raise ValueError(f"readings for {len(found.poses)} scans, models of {len(models)}")
    prior = inclinometer_prior(config, found.poses, found.measured)
    if prior is None:
        return None
    fused: dict[int, bool] = {}

    def needs(k: int) -> bool:
        if k not in fused:
            fused[k] = needs_fusing(registration_model(models.index(k), config))
        return fused[k]

    for index in range(1, len(models)):
        prior.registered_with(index, registration_tilt_deg(config, fuses_scans(config, index, needs)))
    return prior


def relax_revision(
    method: str,
    models: ScanModels,
    revision: Revision,
    fixed: Iterable[int],
    config: PipelineConfig,
    tilt: TiltPrior | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    edge_progress: Callable[[int, int], None] | None = None,
    scheduler: Scheduler | None = None,
) -> RelaxationResult:
    """Relax ``revision``'s poses by ``method`` with the session's settings (``config``): over its
    graph for ``graph``, its sequential links kept as neighbours however little they overlap for
    ``lum`` and ``simultaneous``, ``tilt`` (:func:`revision_tilt_prior`) held where given.

    ``lum`` pairs against the scans' registration models, as ``slam6d run``'s relaxation does
    (:func:`slam6d.pipeline.share_registration_models`): against ``models``' k-NN normals, relaxing
    a run's poses again undid its map (the 250-scan campus: ATE 3.48 to 15.6 cm). They are handed to
    a copy of ``models`` sharing its points and kd-trees, so ``models`` itself (the workbench keeps
    it for its residual views, edge information and the other methods) is left as it was."""
    count = len(revision.poses)
    pairing = models
    if method == "lum":
        pairing = ScanModels(models.points, models.config, [models.index(k) for k in range(len(models))])
        share_registration_models(pairing, config, method)
    return relax_poses(
        method,
        pairing,
        revision.poses,
        graph_edges(count, revision.graph),
        list(fixed),
        config.relax,
        progress=progress,
        cancel=cancel,
        edge_progress=edge_progress,
        links=sequential_links(count, revision.graph),
        scheduler=scheduler,
        tilt=tilt,
    )


def close_revision_loops(
    poses: Sequence[Matrix],
    loops: Sequence[LoopHypothesis],
    keep_tilt: bool,
    cancel: Callable[[], bool] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[Matrix]:
    """Error diffusion over each of ``loops`` in turn (each needs its ICP ``transform``), from
    ``poses``: the workbench's *Close loops* on a revision. With ``keep_tilt`` (the session holds
    an inclinometer's readings) each correction turns only about "up" and keeps its loop end's
    position (:func:`slam6d.attitude.heading_only`), as ``slam6d run``'s loop closing does: a loop's
    relative tilt is a registration's (0.1-0.5° off on the campus's revisits) and would otherwise
    tilt every later scan off its reading. :class:`~slam6d.errors.Cancelled` when ``cancel()``
    turns true; ``progress(done, total)`` after each loop."""
    current = [np.asarray(p, dtype=np.float64) for p in poses]
    for n, loop in enumerate(loops):
        if cancel is not None and cancel():
            raise Cancelled("loop closing cancelled")
        correction = loop_correction(current, loop)
        if keep_tilt:
            correction = heading_only(correction, current[loop.j][:3, 3])
        current = diffuse_loop_correction(current, loop.i, loop.j, correction)
        if progress is not None:
            progress(n + 1, len(loops))
    return current
