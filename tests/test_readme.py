"""README.md (and docs/*.md) as executable documentation: every `pmem` and `curl` line of a
```bash block and every ```python block runs, as written, against the demo's data.

The demo is loaded once per session (`pmem demo --no-serve --workers 0`) into a scratch
database of the test mongod; `pmem` is this checkout's, and `curl` talks to a `pmem serve` of
that database on a free loopback port (the text's 127.0.0.1:8000 is rewritten to it). A line
passes when it exits with 0 and prints something (`curl -o FILE`: writes a non-empty file; a
zip holds at least one exported cluster; a table has no empty part). A Python line
`expression  # 'value'` states a value: it is checked. Only lines that cannot run in CI are
skipped, each with its reason.
"""

from __future__ import annotations

import ast
import json
import os
import re
import secrets
import socket
import subprocess
import sys
import time
import urllib.request
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from pymongo import MongoClient

from .conftest import ROBOSHERLOCK

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```(bash|python)\n(.*?)^```", re.MULTILINE | re.DOTALL)
COMMAND = re.compile(r"^(\w+=\S+\s+)*(pmem|curl)\b")
STATED = re.compile(r"^(?P<code>\S.*?)\s+#\s*(?P<value>'[^']*'|\"[^\"]*\"|-?\d[\d_.]*)\s*$")
SKIPPED = {  # what cannot run in CI, and why
    r"^pmem demo\b": "the demo itself: it loaded this session's data",
    r"\bpmem worker\b": "a worker runs until SIGTERM",
    r"^pmem (serve|consolidate)\b": "runs until stopped (this session serves the data itself)",
    r"^pmem db stop\b": "would stop the embedded mongod of other tests",
    r"^docker compose\b": "docker is not part of CI",
    r"^pip install\b": "CI installs the checkout itself (.ci/run)",
}


@dataclass(frozen=True)
class Example:
    document: Path
    line: int
    language: str
    code: str

    def __str__(self) -> str:
        return f"{self.document.name}:{self.line}"


def examples() -> Iterator[Example]:
    """The bash command lines (continuations joined) and the Python blocks of the documents."""
    for document in DOCUMENTS:
        text = document.read_text()
        for block in BLOCK.finditer(text):
            first = text.count("\n", 0, block.start(2)) + 1
            if block[1] == "python":
                yield Example(document, first, "python", block[2])
                continue
            lines = block[2].replace("\\\n", "\0").splitlines()
            offset = 0
            for line in lines:
                command = line.replace("\0", " ").strip()
                if COMMAND.match(command) or any(re.search(p, command) for p in SKIPPED):
                    yield Example(document, first + offset, "bash", command)
                offset += 1 + line.count("\0")


def skip_reason(example: Example) -> str | None:
    command = COMMAND.sub(lambda m: m[2], example.code) if example.language == "bash" else ""
    return next((why for pattern, why in SKIPPED.items() if re.search(pattern, command)), None)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="session")
def demo(mongo_uri: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict]:
    """The environment of the examples: this checkout's `pmem` first on PATH, the demo's data
    in a scratch database, and its web app on a free port."""
    bin_dir = tmp_path_factory.mktemp("bin")
    shim = bin_dir / "pmem"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m percept_memory "$@"\n')
    shim.chmod(0o755)
    database = f"test_readme_{secrets.token_hex(4)}"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
           "PYTHONPATH": str(ROOT), "MONGODB_URI": mongo_uri, "PMEM_DB": database,
           "PMEM_SHARED_DATA": str(ROBOSHERLOCK),
           "PMEM_DATA_DIR": str(tmp_path_factory.mktemp("data"))}  # similarity indexes go here
    loaded = subprocess.run(["pmem", "demo", "--no-serve", "--workers", "0"], env=env,
                            capture_output=True, text=True, timeout=900)
    assert loaded.returncode == 0, loaded.stderr
    port = free_port()
    server = subprocess.Popen(["pmem", "serve", "--port", str(port)], env=env)
    try:
        wait_until_serving(f"http://127.0.0.1:{port}/api/schema/scene")
        yield {"env": env, "port": port}
    finally:
        server.terminate()
        server.wait(timeout=30)
        with MongoClient(mongo_uri) as client:
            client.drop_database(database)


def wait_until_serving(url: str) -> None:
    deadline = time.monotonic() + 60
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


@pytest.mark.parametrize("example", list(examples()), ids=str)
def test_the_example_runs_as_written(example: Example, demo: dict, tmp_path: Path):
    if reason := skip_reason(example):
        pytest.skip(reason)
    if example.language == "python":
        run_python(example, demo["env"], tmp_path)
    else:
        run_bash(example, demo, tmp_path)


def run_bash(example: Example, demo: dict, folder: Path) -> None:
    command = example.code.replace("127.0.0.1:8000", f"127.0.0.1:{demo['port']}")
    command = re.sub(r"^curl\b", "curl --silent --show-error --fail-with-body", command)
    done = subprocess.run(["bash", "-c", command], cwd=folder, env=demo["env"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{example}: {example.code}\n{done.stdout}\n{done.stderr}"
    written = re.search(r"(?:-o|--out)\s+(\S+)", command)
    if written:
        check_written(folder / written[1], example)
    else:
        answer = done.stdout.strip()
        assert answer not in ("", "[]", "{}") and "(none)" not in answer, \
            f"{example}: no answer\n{done.stdout}"


def check_written(path: Path, example: Example) -> None:
    """A written file is not empty; an export (zip or folder) holds an exported cluster."""
    assert path.exists(), f"{example}: {path.name} not written"
    if path.is_dir():
        manifest = json.loads((path / "manifest.json").read_text())
    else:
        assert path.stat().st_size, f"{example}: {path.name} is empty"
        with zipfile.ZipFile(path) as archive:
            manifest = json.loads(archive.read("manifest.json"))
    assert manifest["exported"] > 0, f"{example}: {manifest}"


def run_python(example: Example, env: dict, folder: Path) -> None:
    for run in ("", " run again"):  # (a newcomer runs it twice)
        done = subprocess.run([sys.executable, "-c", checked(example.code)], cwd=folder,
                              env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{example}{run}:\n{done.stderr}"


def checked(code: str) -> str:
    """The code with each line `expression  # value` turned into an assertion of that value."""
    lines = []
    for line in code.splitlines():
        indent = line[:len(line) - len(line.lstrip())]
        stated = STATED.match(line.strip())
        if stated and is_expression(stated["code"]):
            line = (f"{indent}assert ({stated['code']}) == {stated['value']}, "
                    f"repr({stated['code']})")
        lines.append(line)
    return "\n".join(lines)


def is_expression(code: str) -> bool:
    try:
        ast.parse(code, mode="eval")
    except SyntaxError:
        return False
    return True
