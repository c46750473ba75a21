"""Where the embarrassingly parallel work of a run goes: this process, or a Dask distributed cluster.

A run's stages are sequential (registration needs the previous pose, loop closing the registered
trajectory), but inside several of them the scans are independent: reducing each scan, counting
the overlap of each scan with its candidate neighbours, and in every LUM round the normal-equation
blocks of each scan's pairs. Those go through a :class:`Scheduler`'s :meth:`~Scheduler.map`:

* :class:`SerialScheduler` (the default) calls the function in this process, in order.
* :class:`DaskScheduler` submits one task per item to a Dask distributed cluster: ``local:N`` starts
  a ``LocalCluster`` of N single-threaded worker processes on the loopback interface, and
  ``tcp://HOST:PORT`` connects to a running scheduler (``dask scheduler`` on one machine,
  ``dask worker tcp://HOST:PORT`` on each of the others). Arrays used by many tasks (each scan's
  reduced points or plane sample) are sent once with :meth:`~Scheduler.share` and referred to by
  handle afterwards.

The tasks are pure functions of arrays (no kd-tree or lock crosses the wire: a worker builds the
tree it needs from the points), so a cluster computes exactly what this process would, and the
results are gathered in submission order. Dask is imported only by :func:`open_scheduler` when a
cluster is asked for: a run without ``--scheduler`` starts and imports nothing of it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, TypeVar

from slam6d.errors import Slam6dError

T = TypeVar("T")

__all__ = ["DaskScheduler", "Scheduler", "SchedulerError", "SerialScheduler", "local_workers", "open_scheduler"]


class SchedulerError(Slam6dError):
    """A scheduler address that cannot be parsed or reached."""


class Scheduler(Protocol):
    """Runs independent calls; :meth:`share` makes an array available to them without resending it."""

    def map(self, function: Callable[..., T], *arguments: Sequence[Any]) -> list[T]:
        """``[function(a, b, ...) for a, b, ... in zip(*arguments)]``, in order."""
        ...

    def share(self, items: Sequence[Any]) -> list[Any]:
        """Handles to ``items`` that :meth:`map`'s arguments may hold in their place."""
        ...

    def close(self) -> None: ...


class SerialScheduler:
    """Everything in this process, in order: the reference the distributed results are checked against."""

    def map(self, function: Callable[..., T], *arguments: Sequence[Any]) -> list[T]:
        return [function(*args) for args in zip(*arguments, strict=True)]

    def share(self, items: Sequence[Any]) -> list[Any]:
        return list(items)

    def close(self) -> None:
        pass

    def __repr__(self) -> str:
        return "SerialScheduler()"


class DaskScheduler:
    """A Dask distributed client (see the module docstring); closes the cluster it started."""

    def __init__(self, client: Any, cluster: Any = None, address: str = "") -> None:
        self.client = client
        self.cluster = cluster
        self.address = address

    def map(self, function: Callable[..., T], *arguments: Sequence[Any]) -> list[T]:
        if not arguments or not len(arguments[0]):
            return []
        # pure=False: two items may be equal arrays and still be different scans' work
        futures = self.client.map(function, *arguments, pure=False)
        return list(self.client.gather(futures))

    def share(self, items: Sequence[Any]) -> list[Any]:
        if not items:
            return []
        return list(self.client.scatter(list(items), broadcast=False, hash=False))

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def __repr__(self) -> str:
        return f"DaskScheduler({self.address!r})"


def local_workers(spec: str) -> int | None:
    """N for ``local:N``, None for a cluster address; raises :class:`SchedulerError` for anything else
    (checked before a run reads its scans)."""
    if spec.startswith("local:"):
        try:
            workers = int(spec.split(":", 1)[1])
        except ValueError:
            workers = 0
        if workers < 1:
            raise SchedulerError(f"--scheduler {spec!r}: write local:N with N >= 1 worker processes")
        return workers
    if "://" not in spec:
        raise SchedulerError(f"--scheduler {spec!r}: write local:N or tcp://HOST:PORT")
    return None


def open_scheduler(spec: str | None) -> Scheduler:
    """``None`` -> :class:`SerialScheduler`; ``local:N`` -> a new loopback LocalCluster of N workers;
    ``tcp://HOST:PORT`` (or ``tls://``) -> the running Dask scheduler there."""
    if spec is None or spec in ("", "serial"):
        return SerialScheduler()
    workers = local_workers(spec)
    if workers is not None:
        from dask.distributed import Client, LocalCluster

        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=40,  # logging.ERROR: a run's output stays the run's
        )
        return DaskScheduler(Client(cluster), cluster, spec)
    from dask.distributed import Client

    try:
        client = Client(spec, timeout=10)
    except (OSError, TimeoutError) as exc:
        raise SchedulerError(f"--scheduler {spec}: no Dask scheduler answers there ({exc})") from exc
    return DaskScheduler(client, None, spec)
