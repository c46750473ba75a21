"""``slam6d-workbench``: serve the workbench for a folder of sessions on one port, and hand out access.

``slam6d-workbench [--host ...]`` serves (as always); ``slam6d-workbench token ...`` creates an
access token, ``tokens`` lists them and ``revoke ID`` ends one. The subcommands are recognised by
their first word, so the server's own flags stay where they were (``make run HOST=...``).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from app.jobs import default_job_limit

SUBCOMMANDS = ("serve", "token", "tokens", "revoke")


def serve_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slam6d-workbench", description=__doc__)
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0 to share on the network)")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--sessions-dir", type=Path, default=Path("sessions"), help="folder holding session folders")
    parser.add_argument("--max-upload-mb", type=int, default=512, help="largest accepted scan upload")
    parser.add_argument(
        "--data-root",
        type=Path,
        default=None,
        help="folder that sessions over server folders may read from (without it, only uploads when shared)",
    )
    parser.add_argument(
        "--require-token",
        action="store_true",
        help="ask for an access token even on loopback (always on when bound to another address)",
    )
    parser.add_argument(
        "--max-jobs",
        type=int,
        default=default_job_limit(),
        help="background jobs running at once over all sessions; more wait queued (default: one per core, at least 2)",
    )
    parser.add_argument(
        "--session-memory-budget",
        type=float,
        default=4.0,
        metavar="GB",
        help="scans of opened sessions kept in memory; past it, the least recently used idle sessions "
        "release theirs (read again when needed)",
    )
    parser.add_argument(
        "--viewer-grace",
        type=float,
        default=60.0,
        metavar="SECONDS",
        help="a session's 3D view is stopped this long after its last browser left (started again on return)",
    )
    parser.add_argument(
        "--parse-timeout",
        type=float,
        default=300.0,
        metavar="SECONDS",
        help="longest time parsing an upload or import (or reading a session's scans) may take",
    )
    parser.add_argument(
        "--server-name",
        action="append",
        default=[],
        help="a host name teammates use to reach this server (repeatable; IP addresses always work)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        help="run the parallel stages of registration and relaxation jobs on Dask: local:N starts N worker"
        " processes here, tcp://HOST:PORT joins a running scheduler (as slam6d run --scheduler)",
    )
    return parser


def token_parser(command: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"slam6d-workbench {command}")
    parser.add_argument("--sessions-dir", type=Path, default=Path("sessions"), help="folder holding session folders")
    if command == "token":
        parser.description = "Create an access token; the token is printed on the last line (shown only once)."
        parser.add_argument("--role", required=True, choices=["viewer", "reviewer", "editor", "owner"])
        parser.add_argument("--session", default=None, help="valid on this session only (default: every session)")
        parser.add_argument("--expires", default="never", help="lifetime: 30m, 12h, 7d, 2w or never")
        parser.add_argument("--name", default="", help="who it is for (shown to others and in the journal)")
    elif command == "tokens":
        parser.description = "List the tokens (never their secrets)."
        parser.add_argument("--session", default=None, help="only those valid on this session")
    else:
        parser.description = "Revoke a token by its id (from `tokens`)."
        parser.add_argument("id")
    return parser


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = argv[0] if argv and argv[0] in SUBCOMMANDS else "serve"
    rest = argv[1:] if argv and argv[0] in SUBCOMMANDS else argv
    if command == "serve":
        serve(serve_parser().parse_args(rest))
    else:
        sys.exit(manage_tokens(command, token_parser(command).parse_args(rest)))


def manage_tokens(command: str, args: argparse.Namespace) -> int:
    from app.tokens import Role, TokenError, TokenStore, parse_duration

    if not args.sessions_dir.is_dir():
        print(f"error: sessions folder {args.sessions_dir} does not exist", file=sys.stderr)
        return 2
    store = TokenStore(args.sessions_dir)
    try:
        if command == "token":
            if args.session is not None and not (args.sessions_dir / args.session / "session.toml").is_file():
                print(f"error: no session '{args.session}' in {args.sessions_dir}", file=sys.stderr)
                return 2
            secret, grant = store.issue(Role.parse(args.role), args.session, parse_duration(args.expires), args.name)
            where = f"session '{grant.session}'" if grant.session else "every session"
            print(f"token {grant.id}: {grant.role.name} on {where}, expires {grant.expires or 'never'}")
            print(secret)
        elif command == "tokens":
            for grant in store.grants(args.session):
                state = "revoked" if grant.revoked else f"expires {grant.expires or 'never'}"
                print(f"{grant.id}  {grant.role.name:8}  {grant.session or '*':20}  {grant.name:20}  {state}")
        else:
            grant = store.revoke(args.id)
            print(f"token {grant.id} ({grant.role.name}, {grant.name}) revoked")
    except TokenError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def serve(args: argparse.Namespace) -> None:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # numba threads sleep, not spin, between kernels
    import uvicorn

    from app.guard import is_loopback
    from app.resources import GIB, ResourceLimits
    from app.server import create_app

    if not args.sessions_dir.is_dir():
        print(f"error: sessions folder {args.sessions_dir} does not exist", file=sys.stderr)
        sys.exit(2)
    if args.data_root is not None and not args.data_root.is_dir():
        print(f"error: data root {args.data_root} is not a folder", file=sys.stderr)
        sys.exit(2)
    shared = not is_loopback(args.host)
    try:
        limits = ResourceLimits(
            max_jobs=args.max_jobs,
            session_memory_bytes=int(args.session_memory_budget * GIB),
            viewer_grace_s=args.viewer_grace,
            parse_timeout_s=args.parse_timeout,
        )
    except ValueError as exc:  # named as the user typed it
        flags = {"max_jobs": "--max-jobs", "session_memory_bytes": "--session-memory-budget"}
        flags |= {"viewer_grace_s": "--viewer-grace", "parse_timeout_s": "--parse-timeout"}
        message = str(exc)
        for field_name, flag in flags.items():
            message = message.replace(field_name, flag)
        print(f"error: {message}", file=sys.stderr)
        sys.exit(2)
    if args.scheduler is not None:
        from slam6d.scheduler import SchedulerError, local_workers

        try:
            local_workers(args.scheduler)
        except SchedulerError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)
    app = create_app(
        args.sessions_dir,
        max_upload_mb=args.max_upload_mb,
        bind_host=args.host,
        require_token=args.require_token or shared,
        data_root=args.data_root,
        names=args.server_name,
        limits=limits,
        scheduler=args.scheduler,
    )
    shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    ids = app.state.workbench.session_ids()
    print(f"slam6d workbench: http://{shown}:{args.port}/", flush=True)
    if args.require_token or shared:
        print("  access tokens required: create one with `slam6d-workbench token --role owner`", flush=True)
    if ids:
        print(f"  session '{ids[0]}': http://{shown}:{args.port}/sessions/{ids[0]}", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning", ws_max_size=64 * 1024 * 1024)


if __name__ == "__main__":
    main()
