"""Who may read and write (README: Security), through the real app on the real store: the
Host allow-list, JSON-only and same-origin requests to the API, the generated write token, the
headers on every response."""

from __future__ import annotations

import json
import re
import time

import pytest
import uvicorn
from click.testing import CliRunner
from fastapi.testclient import TestClient
from pydantic import ValidationError

from percept_memory import cli
from percept_memory.memory.settings import Settings
from percept_memory.webui.app import create_app
from percept_memory.webui.guard import served_settings

from .test_ingest import valid_scene
from .test_store import snapshot

SERVER = "http://127.0.0.1:8000"
STAMP = 1_600_000_000_000_000_000


@pytest.fixture(scope="module")
def client(store):
    return TestClient(create_app(store, Settings()), base_url=SERVER)


def scene_body(seed: int) -> str:
    return json.dumps(valid_scene(seed=seed, timestamp=STAMP + seed))


def refused(response, status: int, words: str) -> None:
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert error["status"] == status and words in error["message"]


@pytest.mark.parametrize("content_type", ["text/plain", "application/x-www-form-urlencoded",
                                          "multipart/form-data; boundary=x", None])
def test_a_write_without_a_json_content_type_gets_415_and_stores_nothing(client, store,
                                                                         content_type):
    """What any web page may send without asking: a scene shaped as JSON, but not typed so."""
    headers = {"content-type": content_type} if content_type else {}
    before = snapshot(store)
    response = client.post("/api/scenes", content=scene_body(1), headers=headers)
    refused(response, 415, content_type or "a body without one")
    assert snapshot(store) == before


def test_a_query_in_a_body_is_json_only_too(client):
    response = client.post("/api/clusters", content='{"text": "cereal"}',
                           headers={"content-type": "text/plain"})
    refused(response, 415, "text/plain")
    assert client.post("/api/clusters", json={"text": "cereal"}).status_code == 200


@pytest.mark.parametrize("origin", ["https://evil.example", "null", "http://127.0.0.1:8001",
                                    "http://localhost:8000"])
def test_pages_of_other_origins_get_403_and_store_nothing(client, store, origin):
    """`null` is a page opened from a file or a sandboxed frame; another port or another name
    of this machine is another origin."""
    before = snapshot(store)
    for path, body in (("/api/scenes", scene_body(2)), ("/api/clusters", "{}")):
        response = client.post(path, content=body, headers={
            "origin": origin, "content-type": "application/json"})
        refused(response, 403, f"pages from {origin}")
    assert snapshot(store) == before


def test_the_servers_own_pages_and_allowed_origins_may_write(client, store):
    own = client.post("/api/scenes", content=scene_body(3),
                      headers={"origin": SERVER, "content-type": "application/json"})
    assert own.status_code == 201, own.text
    allowing = TestClient(create_app(store, Settings(
        allowed_origins="https://robots.example, http://localhost:8000")), base_url=SERVER)
    other = allowing.post("/api/scenes", content=scene_body(4), headers={
        "origin": "http://localhost:8000", "content-type": "application/json; charset=utf-8"})
    assert other.status_code == 201, other.text


@pytest.mark.parametrize("path", ["/api/jobs", "/", "/no/such/page"])
def test_other_hosts_get_400_on_every_path(client, path):
    """A site that points its own name at this server (DNS rebinding) reads nothing."""
    refused(client.get(path, headers={"host": "evil.example:8000"}), 400, "evil.example")
    refused(client.get(path, headers={"host": ""}), 400, "host ''")


@pytest.mark.parametrize("host", ["127.0.0.1:8000", "localhost", "LOCALHOST:1234", "[::1]:8000"])
def test_loopback_hosts_are_served_at_any_port(client, host):
    assert client.get("/api/jobs", headers={"host": host}).status_code == 200


def test_allowed_hosts_replace_the_default(store):
    client = TestClient(create_app(store, Settings(allowed_hosts="robot.lan, 10.0.0.7")),
                        base_url="http://robot.lan:8000")
    assert client.get("/api/jobs").status_code == 200
    assert client.get("/api/jobs", headers={"host": "10.0.0.7:8000"}).status_code == 200
    refused(client.get("/api/jobs", headers={"host": "localhost:8000"}), 400, "localhost")


@pytest.mark.parametrize("setting, value", [
    ("allowed_hosts", "127.0.0.1:8939"), ("allowed_hosts", "[::1]:8000"),
    ("allowed_hosts", "http://robot.lan"), ("allowed_origins", "robots.example"),
    ("allowed_origins", "https://robots.example/app"),
])
def test_a_host_or_origin_that_could_never_match_is_refused_at_start(setting, value):
    """Accepted before, such an entry refused every request (400) or every write (403)."""
    said = re.escape(repr(value)) + " is not an? (host name|origin)"
    with pytest.raises(ValidationError, match=said):
        Settings(**{setting: value})


def test_an_origin_is_kept_as_browsers_send_it_and_ipv6_hosts_are_names(store):
    settings = Settings(allowed_origins="https://Robots.example/ ,http://10.0.0.7:8080",
                        allowed_hosts="::1, robot.lan")
    assert settings.allowed_origins == "https://Robots.example,http://10.0.0.7:8080"
    client = TestClient(create_app(store, settings), base_url="http://robot.lan:8000")
    response = client.post("/api/scenes", json=valid_scene(),
                           headers={"origin": "https://robots.example"})
    assert response.status_code == 201, response.text


def test_a_wrong_method_gets_405_with_allow(client):
    response = client.get("/api/scenes")
    assert response.status_code == 405
    assert response.headers["allow"] == "POST"
    assert response.json()["error"]["status"] == 405


@pytest.mark.parametrize("method, path, allowed", [
    ("DELETE", "/api/scenes", "POST"), ("PUT", "/api/jobs", "GET"),
    ("PATCH", "/api/scenes", "POST"), ("HEAD", "/api/scenes", "POST"),
    ("PUT", "/api/clusters", "GET, POST"), ("DELETE", "/api/where-is", "GET, POST")])
def test_a_method_no_route_takes_gets_405_whatever_its_body(client, method, path, allowed):
    """Not 415 for a body without a type: the method is what is wrong."""
    response = client.request(method, path)
    assert response.status_code == 405 and response.headers["allow"] == allowed
    if method != "HEAD":
        assert response.json()["error"]["status"] == 405


def test_head_of_a_stream_ends_with_its_headers(client):
    """The live page's events never end of themselves: a HEAD must not wait for them."""
    started = time.monotonic()
    head = client.head("/live/events")
    assert head.status_code == 200 and head.content == b""
    assert head.headers["content-type"].startswith("text/event-stream")
    assert time.monotonic() - started < 5


@pytest.mark.parametrize("path, same_length", [
    ("/", False), ("/search?text=cup", False),  # (pages whose counts have a time budget)
    ("/api/jobs", True), ("/static/ui/style.css", True)])
def test_head_answers_what_get_would_without_the_body(client, path, same_length):
    got, head = client.get(path), client.head(path)
    assert head.status_code == got.status_code == 200
    assert head.content == b"" and int(head.headers["content-length"]) > 0
    for name in ("content-type", "content-security-policy", *(["content-length"] * same_length)):
        assert head.headers.get(name) == got.headers.get(name), name


@pytest.mark.parametrize("method, path, headers", [
    ("GET", "/api/jobs", {}),
    ("GET", "/", {}),
    ("GET", "/static/ui/style.css", {}),
    ("GET", "/no/such/page", {}),
    ("GET", "/api/jobs", {"host": "evil.example"}),
    ("POST", "/api/scenes", {"content-type": "text/plain"}),
])
def test_every_response_has_the_security_headers(client, method, path, headers):
    response = client.request(method, path, headers=headers)
    assert response.headers["referrer-policy"] == "no-referrer"
    assert response.headers.get_list("x-content-type-options") == ["nosniff"]


def test_serving_beyond_loopback_without_a_token_makes_one_up(store, capsys):
    settings = served_settings(Settings(), "0.0.0.0")
    printed = capsys.readouterr().err
    assert settings.token and f"Authorization: Bearer {settings.token}" in printed
    assert served_settings(Settings(), "0.0.0.0").token != settings.token  # one per run
    assert settings.allowed_hosts == "127.0.0.1,localhost,::1,0.0.0.0"

    client = TestClient(create_app(store, settings), base_url=SERVER)
    assert client.post("/api/scenes", content=scene_body(5),
                       headers={"content-type": "application/json"}).status_code == 401
    assert client.post("/api/scenes", content=scene_body(5), headers={
        "content-type": "application/json",
        "authorization": f"Bearer {settings.token}"}).status_code == 201
    assert client.get("/api/jobs").status_code == 200  # reads stay open
    assert client.post("/api/clusters", json={"text": "cereal"}).status_code == 200


def test_pmem_serve_on_all_interfaces_needs_a_token_for_writes(mongo_uri, db_name, monkeypatch):
    """The CLI's wiring, with the server's run replaced by a few requests and its socket by
    none: nothing listens here."""
    answers = []

    def run(server, sockets):
        client = TestClient(server.config.app, base_url=SERVER)
        answers.append(client.post("/api/scenes", content=scene_body(6),
                                   headers={"content-type": "application/json"}).status_code)
        answers.append(client.get("/api/jobs").status_code)

    monkeypatch.setattr(uvicorn.Server, "run", run)
    monkeypatch.setattr(cli, "listening", lambda host, port: None)
    result = CliRunner().invoke(cli.main, ["serve", "--host", "0.0.0.0"],
                                env={"MONGODB_URI": mongo_uri, "PMEM_DB": db_name})
    assert result.exit_code == 0, result.output
    assert answers == [401, 200]
    assert "Authorization: Bearer " in result.stderr


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "localhost", "::1"])
def test_serving_on_loopback_needs_no_token(capsys, host):
    settings = served_settings(Settings(), host)
    assert settings.token is None and capsys.readouterr().err == ""
    assert host in settings.allowed_hosts.split(",")


def test_a_configured_token_and_hosts_are_kept(capsys):
    settings = served_settings(Settings(token="s3cret", allowed_hosts="robot.lan"), "0.0.0.0")
    assert (settings.token, settings.allowed_hosts) == ("s3cret", "robot.lan")
    assert capsys.readouterr().err == ""


def test_an_empty_token_is_refused():
    """Else `Authorization: Bearer ` with nothing after it would be the right token."""
    with pytest.raises(ValidationError, match="token"):
        Settings(token="")
