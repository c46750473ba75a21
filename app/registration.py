"""Running the engine's registration pipeline for a session, as a job or step by step.

Engine parameters come from ``[engine]`` in session.toml, overridden per run, parsed by the engine
(:func:`slam6d.engine_settings.pipeline_config`, as ``slam6d run`` does); unknown names are refused. The pipeline works on its own copy of the
scans so the 3D view keeps showing the committed revision until the run is stored.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from app.editing.loops import hypotheses_entry
from app.errors import PartialResultError
from app.jobs import Cancel, Progress, Work
from app.traces import TraceRecorder
from app.workbench import Workbench
from slam6d import pipeline
from slam6d.engine_settings import pipeline_config
from slam6d.errors import Slam6dError
from slam6d.scan import Scan, ScanSequence
from slam6d.session_relaxation import registration_readings
from slam6d.trace import to_jsonable


def working_copy(sequence: ScanSequence) -> ScanSequence:
    """Scans sharing the (read-only) point arrays but with their own poses."""
    scans = [
        Scan(s.points, s.pose.copy(), name=s.name, source=s.source, intensity=s.intensity, has_pose=s.has_pose)
        for s in sequence.scans
    ]
    return ScanSequence(scans, sequence.convention, sequence.source, sequence.format_name)


def accepted_loops(report: Any) -> list[dict[str, Any]]:
    loops = getattr(report, "loops", None) or []
    return [
        {
            "i": int(h.i),
            "j": int(h.j),
            "kind": "loop",
            "fitness": float(getattr(h, "fitness", 0.0)),
            "rms": to_jsonable(float(getattr(h, "rms", float("nan")))),
            "transform": to_jsonable(getattr(h, "transform", None)),
        }
        for h in loops
        if getattr(h, "accepted", True)
    ]


def registration_job(workbench: Workbench, session_id: str, author: str, parameters: dict[str, Any]) -> Work:
    """A job that runs the whole pipeline and commits its poses as a new revision."""
    state = workbench.state(session_id)
    config = pipeline_config(state.session.config.engine, parameters)

    def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
        sequence = working_copy(state.sequence(lambda d, t: progress("reading scans", d, t)))
        base = state.session.revision  # the revision the run starts from (the scans follow the head)
        measured = [s.has_pose for s in sequence.scans]
        readings = registration_readings(state.session, config, measured)  # revision 0's, not the head's
        runner = pipeline.Pipeline(sequence, config, scheduler=workbench.scheduler(), readings=readings)
        recorder = TraceRecorder()
        run = RunCommit(workbench, session_id, author, runner, recorder, {"config": to_jsonable(config)}, base)
        try:
            report = recorder.attach(runner).run(progress, cancel)
        except Slam6dError as exc:
            partial = run.partial_error(exc)
            if partial is None:
                raise
            raise partial from exc
        return run.store() | {"report": to_jsonable(report)}

    return work


@dataclass(frozen=True)
class RunCommit:
    """A registration run (a job's, or the 3D view's stepped one) and where its poses go when it ends.

    Both ways of running registration end the same way: finished, the poses become a revision; failed
    part-way, the poses of the stages before the failure do, so that nobody starts over.
    """

    workbench: Workbench
    session_id: str
    author: str
    runner: pipeline.Pipeline
    recorder: TraceRecorder
    parameters: dict[str, Any]
    base: int | None = None  # the revision the run started from; a scan someone moved meanwhile refuses it (409)

    def store(self, failure: dict[str, Any] | None = None) -> dict[str, Any]:
        """Commit the run's poses with its trace file named in the journal, then its loops for review;
        ``failure``: what the journal entry also records of a stage that failed."""
        session = self.workbench.state(self.session_id).session
        meta = {"author": self.author, "final_poses": to_jsonable(self.runner.poses)}
        name = self.recorder.save(session, self.runner.odometry, meta)
        graph = {"loops": accepted_loops(self.runner.report), "removed": []}
        parameters = {**self.parameters, **(failure or {}), "trace": name}
        revision = self.workbench.commit(
            self.session_id, self.runner.poses, self.author, "register", parameters, graph=graph, base=self.base
        )
        report = self.runner.report
        if report is not None and report.loops:
            session.journal.append(self.author, "loop_hypotheses", hypotheses_entry(report.loops))
            self.workbench.notify(self.session_id)
        return {"revision": revision, "trace": name}

    def keep_partial(self) -> dict[str, Any] | None:
        """Commit the poses of a run whose stage failed (or was cancelled) as a revision, with the failure
        (stage, reason) and the connected components in its journal entry, so the operator can correct
        it by hand instead of starting over. None when the run has no report of a failure to keep."""
        report = getattr(self.runner, "report", None)
        failure = getattr(report, "failure", None)
        if report is None or failure is None:
            return None
        kept = {"failure": to_jsonable(failure), "components": [list(c) for c in getattr(report, "components", [])]}
        stored = self.store(kept)
        components = kept["components"]
        pieces = f" in {len(components)} connected components" if len(components) > 1 else ""
        message = (
            f"the {failure.stage} stage failed; the poses of the stages before it are kept as revision "
            f"{stored['revision']}{pieces}"
        )
        return stored | kept | {"kept": message, "report": to_jsonable(report)}

    def partial_error(self, failed: Slam6dError) -> PartialResultError | None:
        """The error to raise for a run that ``failed``: naming the revision its poses so far were kept
        as, or None when there is nothing to keep (raise ``failed`` itself)."""
        kept = self.keep_partial()
        return None if kept is None else PartialResultError(f"{failed} — {kept['kept']}", kept)
