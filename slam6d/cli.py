"""The ``slam6d`` command line: thin wrappers that parse options and call the engine."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from slam6d.errors import Slam6dError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="6D SLAM for 3D laser scans (Kurt3D method).")
err = Console(stderr=True)


@contextmanager
def progress_bar(description: str) -> Iterator[callable]:  # type: ignore[valid-type]
    """A rich progress bar on stderr; yields ``update(done, total)`` for the engine's callbacks."""
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err,
        transient=False,
        disable=not err.is_terminal,
    ) as progress:
        task = progress.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        yield update


FormatOption = Annotated[str | None, typer.Option("--format", "-f", help="Input format name (see `slam6d formats`).")]


@app.command()
def formats() -> None:
    """List the scan formats ``--format`` accepts."""
    from slam6d.io.registry import format_names, get_format

    for name in format_names():
        fmt = get_format(name)
        typer.echo(f"{name:10s} {' '.join(fmt.suffixes):18s} {fmt.description}")


# -- commands are added below, one per engine entry point --


def main() -> None:
    """Console entry point: engine errors become one clear line and exit code 2, not a traceback."""
    try:
        app()
    except Slam6dError as exc:
        err.print(f"[red]error:[/red] {exc}")
        sys.exit(2)


if __name__ == "__main__":
    main()
