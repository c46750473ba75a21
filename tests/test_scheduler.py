"""A run on a Dask cluster, or from the on-demand scan store, lands where the plain serial run does."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam6d.pipeline import Pipeline, PipelineConfig
from slam6d.scan import Scan, ScanSequence
from slam6d.scan_store import ScanStore
from slam6d.scheduler import DaskScheduler, SchedulerError, SerialScheduler, open_scheduler
from tests.cli_process import loaded_by
from tests.simulated_loop import simulated_loop

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def loop_sequence() -> ScanSequence:
    """A small loop whose points are exact in float32, so a store holds them unchanged."""
    sim = simulated_loop(scans=8, points=20000, seed=1, loop_length=16.0, loop_width=10.0)
    scans = [
        Scan(s.points.astype(np.float32).astype(np.float64), s.pose.copy(), name=s.name, has_pose=s.has_pose)
        for s in sim.sequence
    ]
    return ScanSequence(scans)


@pytest.fixture(scope="module")
def serial_poses(loop_sequence: ScanSequence) -> list[np.ndarray]:
    pipeline = Pipeline(loop_sequence, PipelineConfig())
    report = pipeline.run()
    assert report.loops_closed and report.relaxation_iterations > 0  # the run exercises every stage
    return pipeline.poses


def test_dask_cluster_run_equals_the_serial_run(
    loop_sequence: ScanSequence, serial_poses: list[np.ndarray], tmp_path: Path
) -> None:
    """Two in-process workers (no network: Dask's in-process transport) compute the reduction (from the store, read by
    the workers) and every LUM round's blocks; the poses equal the serial run's."""
    from dask.distributed import Client, LocalCluster

    store = ScanStore(ScanStore.create(tmp_path / "store", iter(loop_sequence.scans)), budget=10**9)
    light = ScanSequence([store.scan(k, with_points=False) for k in range(len(store))])
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        scheduler = DaskScheduler(client)
        pipeline = Pipeline(light, PipelineConfig(), store=store, scheduler=scheduler)
        pipeline.run()
        assert pipeline.summaries[3].points == len(loop_sequence[3])
    for got, want in zip(pipeline.poses, serial_poses, strict=True):
        np.testing.assert_allclose(got, want, atol=1e-6)


def test_store_backed_run_equals_the_in_memory_run(
    loop_sequence: ScanSequence, serial_poses: list[np.ndarray], tmp_path: Path
) -> None:
    store = ScanStore(ScanStore.create(tmp_path / "store", iter(loop_sequence.scans)), budget=3 * 20000 * 24)
    light = ScanSequence([store.scan(k, with_points=False) for k in range(len(store))])
    pipeline = Pipeline(light, PipelineConfig(), store=store)
    report = pipeline.run()
    assert store.peak_bytes <= store.budget and store.loads == len(store)
    assert report.peak_memory_bytes > 0
    for got, want in zip(pipeline.poses, serial_poses, strict=True):
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_serial_scheduler_maps_in_order() -> None:
    scheduler = SerialScheduler()
    assert scheduler.map(divmod, [7, 9], [2, 4]) == [(3, 1), (2, 1)]
    assert scheduler.share([1, 2]) == [1, 2]
    assert isinstance(open_scheduler(None), SerialScheduler)


@pytest.mark.parametrize("spec", ["local:0", "local:x", "cluster", "host:8786"])
def test_bad_scheduler_addresses_are_refused(spec: str) -> None:
    with pytest.raises(SchedulerError, match="--scheduler"):
        open_scheduler(spec)


def test_cli_run_on_local_workers_and_without_dask(tmp_path: Path) -> None:
    """`slam6d run --scheduler local:2` (two worker processes) writes the poses the serial run writes;
    the serial run imports nothing of Dask."""
    from slam6d.simulate import SimulationConfig, simulate_session

    session = tmp_path / "loop"
    simulate_session(
        session, SimulationConfig(seed=4, scans=10, points_per_scan=20000, loop_length=16.0, loop_width=10.0)
    )
    poses = {}
    budget = ["--memory-budget", "50MB"]  # the workers read the scans from OUT/scan_store themselves
    for name, extra in (("serial", []), ("cluster", ["--scheduler", "local:2"])):
        out = tmp_path / name
        loaded = loaded_by("run", str(session), "--format", "uos", "--out", str(out), *budget, *extra)
        assert ("dask" in loaded) == (name == "cluster"), loaded
        poses[name] = np.loadtxt(out / "poses_kitti.txt")
        report = json.loads((out / "report.json").read_text())
        assert report["scan_store"]["peak_bytes"] <= 50 * 10**6 and report["peak_memory_bytes"] > 0
    np.testing.assert_allclose(poses["cluster"], poses["serial"], atol=1e-4)  # centimetres


def test_cli_refuses_a_bad_scheduler_or_budget_before_reading(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from slam6d.cli import app

    for option, value, message in (("--scheduler", "cluster", "local:N"), ("--memory-budget", "lots", "memory size")):
        result = CliRunner().invoke(app, ["run", str(tmp_path), "--out", str(tmp_path / "out"), option, value])
        assert result.exit_code == 2 and message in result.output, result.output
