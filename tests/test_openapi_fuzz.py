"""schemathesis over the workbench's own ``/openapi.json``: no server error and no answer that
contradicts the schema (status, content type, body), for generated valid and invalid requests.

In-process against the ASGI app (loopback only, no viser servers), with a bounded number of
examples per operation so the run stays within a couple of minutes.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, settings

from app.server import create_app
from tests.session_fixtures import corridor_session

EXAMPLES_PER_OPERATION = 8
SESSIONS = Path(__file__).resolve().parent.parent / "test-artifacts" / "openapi-fuzz-sessions"


def _app():  # type: ignore[no-untyped-def]
    import shutil

    shutil.rmtree(SESSIONS, ignore_errors=True)
    corridor_session(SESSIONS, scans=3, points=300)
    # in-process requests name the host "testserver": a name this server answers to here
    return create_app(SESSIONS, viewers=False, max_upload_mb=1, names=("testserver",))


schema = schemathesis.openapi.from_asgi("/openapi.json", _app())
CHECKS = [
    schemathesis.checks.not_a_server_error,
    schemathesis.checks.status_code_conformance,
    schemathesis.checks.content_type_conformance,
    schemathesis.checks.response_schema_conformance,
]


@pytest.mark.filterwarnings("ignore")
@schema.parametrize()
@settings(
    max_examples=EXAMPLES_PER_OPERATION,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=list(HealthCheck),
)
def test_api_answers_what_its_schema_says(case: schemathesis.Case) -> None:
    case.call_and_validate(checks=CHECKS)
