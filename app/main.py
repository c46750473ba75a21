"""``slam6d-workbench``: serve the workbench for a folder of sessions on one port."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="slam6d-workbench", description=__doc__)
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0 to share on the network)")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--sessions-dir", type=Path, default=Path("sessions"), help="folder holding session folders")
    parser.add_argument("--max-upload-mb", type=int, default=512, help="largest accepted scan upload")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # numba threads sleep, not spin, between kernels
    import uvicorn

    from app.server import create_app

    if not args.sessions_dir.is_dir():
        print(f"error: sessions folder {args.sessions_dir} does not exist", file=sys.stderr)
        sys.exit(2)
    app = create_app(args.sessions_dir, max_upload_mb=args.max_upload_mb)
    shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    ids = app.state.workbench.session_ids()
    print(f"slam6d workbench: http://{shown}:{args.port}/", flush=True)
    if ids:
        print(f"  session '{ids[0]}': http://{shown}:{args.port}/sessions/{ids[0]}", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning", ws_max_size=64 * 1024 * 1024)


if __name__ == "__main__":
    main()
