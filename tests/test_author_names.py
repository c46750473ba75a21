"""Names in any script: X-Author as percent-encoded UTF-8, checked, and the same name everywhere it shows."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from app.tokens import Role, TokenError, TokenStore
from app.view.names import MAX_NAME, InvalidNameError, checked_name, name_from_cookie, name_from_header
from tests.session_fixtures import corridor_session

SESSION = "corridor"
API = f"/api/sessions/{SESSION}"
NAMES = ("张伟", "Łukasz", "Zoë O'Brien", "Ἀριστοτέλης")


def encoded(name: str) -> str:
    """What the page sends: RFC 8187's extended value, as ``encodeURIComponent`` makes it."""
    return "UTF-8''" + quote(name, safe="!'()*-._~")


@pytest.fixture
def sessions_dir(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=1500, odometry_noise=0.1, engine={"voxel_size": 0.1})
    return root


@pytest.fixture
def open_server(sessions_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(sessions_dir, viewers=False), base_url="http://127.0.0.1") as client:
        yield client


def move_scan_1(client: TestClient, headers: dict[str, str]) -> int:
    pose = client.app.state.workbench.current_poses(SESSION)[1].copy()  # type: ignore[attr-defined]
    pose[0, 3] += 0.01
    answer = client.post(f"{API}/scans/1/pose", json={"pose": pose.tolist()}, headers=headers)
    return answer.status_code


# ------------------------------------------------------------------ decoding and checking


@pytest.mark.parametrize("name", NAMES)
def test_a_percent_encoded_utf8_header_gives_the_name_back(name: str) -> None:
    assert name_from_header(encoded(name)) == name
    assert name_from_header(encoded(name).replace("UTF-8''", "utf-8''")) == name  # the charset is caseless
    # curl -H sends raw UTF-8 bytes, which the server reads as Latin-1 characters
    assert name_from_header(name.encode("utf-8").decode("latin-1")) == name


def test_plain_latin1_and_ascii_headers_are_taken_as_they_come() -> None:
    assert name_from_header("  ana ") == "ana"
    assert name_from_header("José") == "José"  # one Latin-1 byte é: not UTF-8, so Latin-1 text
    assert name_from_header("50%20off") == "50%20off"  # no RFC 8187 prefix: no percent-decoding


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        ("UTF-8''bob%07", "U+0007"),
        ("UTF-8''a%0Ab", "U+000A"),
        ("UTF-8''%E2%80%AEnimda", "U+202E"),  # right-to-left override: would disguise the name
        ("UTF-8''%FF%FE", "not percent-encoded UTF-8"),
        ("UTF-8''" + "x" * (MAX_NAME + 1), f"at most {MAX_NAME} characters"),
        ("UTF-8''" + quote("张" * (MAX_NAME + 1)), f"at most {MAX_NAME} characters"),
    ],
)
def test_names_with_control_characters_bad_encoding_or_too_long_are_refused(raw: str, why: str) -> None:
    with pytest.raises(InvalidNameError, match=re.escape(why)):
        name_from_header(raw)


def test_the_name_cookie_is_decoded_the_same_way_and_an_invalid_one_ignored() -> None:
    assert name_from_cookie(quote("张伟")) == "张伟"
    assert name_from_cookie(quote("bob\x07")) == ""
    assert name_from_cookie("%FF") == ""
    assert checked_name("张" * MAX_NAME) == "张" * MAX_NAME  # characters are counted, not bytes


def test_a_token_cannot_be_named_with_control_characters(tmp_path: Path) -> None:
    store = TokenStore(tmp_path)
    with pytest.raises(TokenError, match=r"name: .*U\+001B"):
        store.issue(Role.viewer, name="evil\x1b[31m")
    assert store.issue(Role.viewer, name="张伟")[1].name == "张伟"


# ------------------------------------------------------------------ over HTTP


@pytest.mark.parametrize("name", ["张伟", "Łukasz"])
def test_an_encoded_name_is_the_same_in_journal_comments_and_me(open_server: TestClient, name: str) -> None:
    headers = {"X-Author": encoded(name)}
    assert open_server.get("/api/me", headers=headers).json()["name"] == name
    assert move_scan_1(open_server, headers) == 200
    assert open_server.get(f"{API}/journal").json()[-1]["author"] == name
    added = open_server.post(f"{API}/comments", json={"anchor": {"scan": 1}, "text": "look"}, headers=headers)
    assert added.status_code == 201, added.text
    assert added.json()["author"] == name
    assert open_server.get(f"{API}/comments").json()[0]["author"] == name


def test_an_invalid_name_is_refused_with_422_naming_x_author_and_nothing_applied(open_server: TestClient) -> None:
    assert move_scan_1(open_server, {"X-Author": "ana"}) == 200  # something to undo
    before = open_server.get(f"{API}/journal").json()
    for raw in ("UTF-8''bob%07", "UTF-8''" + "x" * (MAX_NAME + 1), "UTF-8''%C3"):
        refused = open_server.post(f"{API}/undo", json={}, headers={"X-Author": raw})
        assert refused.status_code == 422, refused.text
        assert refused.json()["detail"][0]["loc"] == ["header", "X-Author"]
        assert move_scan_1(open_server, {"X-Author": raw}) == 422
    assert open_server.get(f"{API}/journal").json() == before  # no move, no undo
    assert open_server.get("/api/me", headers={"X-Author": "UTF-8''a%00"}).status_code == 422


def test_a_token_holders_non_latin_name_is_kept_whatever_the_page_sends(sessions_dir: Path) -> None:
    app = create_app(sessions_dir, viewers=False, require_token=True)
    with TestClient(app, base_url="http://127.0.0.1") as client:
        secret, _ = app.state.tokens.issue(Role.editor, SESSION, name="张伟")
        headers = {"Authorization": f"Bearer {secret}", "X-Author": encoded("someone else")}
        assert client.get("/api/me", headers=headers).json()["name"] == "张伟"
        assert move_scan_1(client, headers) == 200
        assert client.get(f"{API}/journal", headers=headers).json()[-1]["author"] == "张伟"
        added = client.post(f"{API}/comments", json={"anchor": {"scan": 0}, "text": "ok"}, headers=headers)
        assert added.json()["author"] == "张伟"
        # a token's holder is the token's name: a malformed X-Author from an old page is not even read
        bad = {"Authorization": f"Bearer {secret}", "X-Author": "UTF-8''%07"}
        assert client.get("/api/me", headers=bad).json()["name"] == "张伟"
