"""`pmem info`, the CLI's errors and conventions, against real MongoDB servers."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time

import click
import numpy as np
import pytest
from click.testing import CliRunner
from pymongo import MongoClient

from percept_memory.cli import main
from percept_memory.ingest import synthetic
from percept_memory.ingest.scene_log import write_scene_log
from percept_memory.memory.mongod import find_mongod

from .conftest import ROBOSHERLOCK
from .test_mongod import free_port


def pmem(*args: str, **env: str | None):
    return CliRunner().invoke(main, list(args), env=env)


def test_info_counts_what_the_store_holds(store, mongo_uri, db_name, kitchen_rgb):
    store.put_scene(synthetic.scene(np.random.default_rng(4), 1_000, 3, kitchen_rgb))
    result = pmem("info", "--json", MONGODB_URI=mongo_uri, PMEM_DB=db_name)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["database"] == db_name
    assert report["collections"]["scenes"] == 1
    assert report["collections"]["clusters"] == 3
    assert report["types"]["pm.annotation.WebLookup"] == 9  # 3 per synthetic cluster
    assert report["types"]["pm.hypothesis.ImageROI"] == 3

    human = pmem("info", MONGODB_URI=mongo_uri, PMEM_DB=db_name)
    assert human.exit_code == 0
    assert "pm.annotation.Classification" in human.stdout
    assert "clusters" in human.stdout


def test_info_on_an_unreachable_server_says_what_to_do():
    uri = f"mongodb://reader:s3cret@127.0.0.1:{free_port()}/?serverSelectionTimeoutMS=300"
    result = pmem("info", MONGODB_URI=uri)
    assert result.exit_code == 1
    assert "cannot use MongoDB at" in result.stderr and "MONGODB_URI" in result.stderr
    assert "s3cret" not in result.stderr and "Traceback" not in result.output


@pytest.fixture
def standalone_mongod(tmp_path):
    """A real mongod started without --replSet, as many installations run it."""
    port = free_port()
    process = subprocess.Popen(
        [str(find_mongod()), "--dbpath", str(tmp_path), "--port", str(port),
         "--bind_ip", "127.0.0.1", "--quiet", "--logpath", str(tmp_path / "log")],
    )
    uri = f"mongodb://127.0.0.1:{port}/?serverSelectionTimeoutMS=20000"
    with MongoClient(uri) as client:
        for _ in range(200):
            try:
                client.admin.command("ping")
                break
            except Exception:
                time.sleep(0.1)
    yield uri
    process.terminate()
    process.wait(30)


def test_a_standalone_server_is_refused_with_the_fix(standalone_mongod):
    result = pmem("info", MONGODB_URI=standalone_mongod)
    assert result.exit_code == 1
    assert "replica set" in result.stderr and "--replSet" in result.stderr


def test_import_commands_summarise_and_never_duplicate(mongo_uri, db_name, tmp_path, store):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    first = pmem("import", "rgbd", str(ROBOSHERLOCK / "samples" / "low_noise"), **env)
    assert first.exit_code == 0, first.output
    assert "2 new scenes, 0 stored before, 17 clusters" in first.stdout
    assert "pm.annotation.ColorHistogram" in first.stdout
    assert "scene times: 2 from the modification times of the cloud files" in first.stdout
    again = pmem("import", "rgbd", str(ROBOSHERLOCK / "samples" / "low_noise"), **env)
    assert "0 new scenes, 2 stored before" in again.stdout

    dump = pmem("import", "robosherlock", str(ROBOSHERLOCK / "mongodump" / "IJRRScenes"), **env)
    assert "11 new scenes" in dump.stdout, dump.output
    not_a_dump = pmem("import", "robosherlock", str(tmp_path), **env)
    assert not_a_dump.exit_code == 1 and "holds no cas.bson" in not_a_dump.stderr
    assert "Traceback" not in not_a_dump.output
    both = pmem("import", "robosherlock", str(tmp_path), "--uri", mongo_uri, **env)
    assert "FOLDER, or --uri and --db" in error_line(both)

    write_scene_log([synthetic.scene(np.random.default_rng(1), 5_000 + i, 2) for i in range(3)],
                    tmp_path / "log")
    log = pmem("import", "scene-log", str(tmp_path / "log"), **env)
    assert "3 new scenes, 0 stored before, 6 clusters" in log.stdout, log.output
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "scenes.jsonl").write_text('{"robot": "pr2"}\n')
    bad = pmem("import", "scene-log", str(tmp_path / "bad"), **env)
    assert bad.exit_code == 1
    assert "scenes.jsonl:1: timestamp: Field required" in bad.stderr
    assert "Traceback" not in bad.output


def test_demo_loads_real_data_and_the_kitchen_week_once(mongo_uri, db_name):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": f"{db_name}_demo"}
    try:
        first = pmem("demo", "--no-serve", "--days", "2", **env)
        assert first.exit_code == 0, first.output
        for source in ("samples/kitchen", "samples/low_noise", "mongodump/IJRRScenes",
                       "mongodump/PnP09ObjSymbolicGTFixed", "kitchen week (2 days)"):
            assert f"{source}: " in first.stdout
        assert "mongodump/PnP09ObjSymbolicGTFixed: 35 new scenes" in first.stdout
        second = pmem("demo", "--no-serve", "--days", "2", **env)
        assert " 0 new scenes" in second.stdout and "1 new" not in second.stdout
        with MongoClient(mongo_uri) as client:
            scenes = client[env["PMEM_DB"]]["scenes"]
            keys = {(d["robot"], d["timestamp"]) for d in scenes.find({}, {"_id": 0})}
            assert scenes.count_documents({}) == len(keys)
        none = pmem("demo", "--no-serve", "--days", "0", **env)  # (0: no week, as it says)
        assert none.exit_code == 0 and "kitchen week" not in none.stdout, none.output
    finally:
        with MongoClient(mongo_uri) as client:
            client.drop_database(env["PMEM_DB"])


def test_every_command_shows_an_example_in_its_help():
    def commands(group, path):
        for name in group.list_commands(None):
            command = group.get_command(None, name)
            yield [*path, name]  # (a group too: `pmem query --help`)
            if isinstance(command, click.Group):
                yield from commands(command, [*path, name])

    for path in commands(main, []):
        shown = CliRunner().invoke(main, [*path, "--help"])
        assert shown.exit_code == 0, path
        example = re.split(r"Examples?:\n", shown.output, maxsplit=1)[1].splitlines()[0].strip()
        assert example.startswith(("pmem ", "export MONGODB_URI=$(pmem", "PMEM_")), path
        assert " ".join(path) in example, path


def test_the_cli_starts_without_the_web_app_opencv_or_the_demo_generator():
    """`pmem --help` and `pmem query` must start fast: the heavy modules load in the commands
    that need them."""
    loaded = subprocess.run(
        [sys.executable, "-c", "import sys; from percept_memory.cli import main; "
         "main(['query', 'where-is', '--help'], standalone_mode=False); "
         "print(' '.join(sys.modules))"], capture_output=True, text=True, check=True)
    modules = set(loaded.stdout.split("\n")[-2].split())
    assert not modules & {"fastapi", "uvicorn", "percept_memory.webui.app",
                          "percept_memory.demo.kitchen_week", "percept_memory.ingest.rgbd",
                          "percept_memory.ingest.service", "scipy"}


def test_job_states_are_those_of_the_queue():
    from percept_memory.cli import JOB_STATES
    from percept_memory.ingest.jobs import STATES

    assert JOB_STATES == STATES


def error_line(result) -> str:
    """The one line an expected failure prints: `Error: ...`, exit code 1, no traceback."""
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    assert "Traceback" not in result.output
    return lines[0]


@pytest.mark.parametrize("args, words", [
    (["jobs", "--state", "bogus"], "'bogus' is not one of"),
    (["export", "coco"], "Missing option '--out'. (see `"),  # (`pmem export --help`)
    (["query", "catalogue", "--limit", "0"], "0 is not in the range"),
    (["correct", "split", "5f0000000000000000000001"], "Missing"),
    (["nosuch"], "No such command 'nosuch'"),
    (["serve", "--port", "99999"], "99999 is not in the range 1<=x<=65535"),
    (["demo", "--days", "-1", "--no-serve"], "-1 is not in the range x>=0"),
])
def test_a_command_line_click_cannot_parse_is_one_error_line_and_exit_1(args, words):
    assert words in error_line(pmem(*args))


def test_a_command_that_finds_nothing_to_do_says_so_and_exits_1(mongo_uri):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": "pmem_test_nothing_to_do"}
    try:
        assert "no scene to reconsolidate" in error_line(pmem("reconsolidate", **env))
        assert "nothing to reindex: no cluster is stored" in error_line(pmem("reindex", **env))
        reported = pmem("pipeline", "--retry", **env)  # (a report, with a retry before it)
        assert reported.exit_code == 0 and reported.stderr == (
            "no held scene to retry\nno scene is stored yet: no map to consolidate\n")
    finally:
        MongoClient(mongo_uri).drop_database(env["PMEM_DB"])


def test_a_bad_database_name_and_a_port_in_use_are_one_error_line(mongo_uri):
    assert "PMEM_DB 'a/b' is not a MongoDB database name" in error_line(
        pmem("info", MONGODB_URI=mongo_uri, PMEM_DB="a/b"))
    # a setting beyond what works is refused by its variable's name, before anything runs
    # (inf and 1e12 crashed on a timedelta, or stopped the consolidator's thread, later)
    for variable, value, said in (("PMEM_MAP_LEASE_S", "inf", "a finite number"),
                                  ("PMEM_JOB_LEASE_S", "1e12", "less than or equal to 86400"),
                                  ("PMEM_MAX_REQUEST_MB", "nan", "a finite number")):
        assert error_line(pmem("info", MONGODB_URI=mongo_uri, **{variable: value})) == (
            f"Error: {variable}: Input should be {said}")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = str(taken.getsockname()[1])
        line = error_line(pmem("serve", "--port", port, MONGODB_URI=mongo_uri))
    assert line == f"Error: cannot listen on 127.0.0.1:{port}: Address already in use"


def test_the_demos_samples_are_at_the_same_times_from_a_copy_of_the_data(tmp_path,
                                                                         monkeypatch):
    """A fresh clone or a copy of the data has new file times: samples put at them were
    stored again by the demo run again ("Running it again adds nothing")."""
    import shutil

    from percept_memory.cli import demo_sources

    def times() -> list[int]:
        return [scene.timestamp for name, scenes in demo_sources(days=0)
                if name.startswith("samples/") for scene in scenes]

    monkeypatch.setenv("PMEM_SHARED_DATA", str(ROBOSHERLOCK))
    original = times()
    copy = tmp_path / "robosherlock"
    shutil.copytree(ROBOSHERLOCK / "samples", copy / "samples", copy_function=shutil.copy)
    (copy / "mongodump").mkdir()
    monkeypatch.setenv("PMEM_SHARED_DATA", str(copy))
    assert len(original) == 3 and times() == original


def test_serve_stops_on_sigterm_while_a_live_page_listens(mongo_uri):
    """The live page's event stream ends only when its client goes: a tab left open kept
    the server up for as long (a SIGTERM waited 59 s for a curl to give up)."""
    from .test_readme import wait_until_serving
    port = free_port()
    env = {**os.environ, "MONGODB_URI": mongo_uri, "PMEM_DB": "pmem_test_serve_stops"}
    server = subprocess.Popen([sys.executable, "-m", "percept_memory", "serve", "--port",
                               str(port)], env=env, stderr=subprocess.PIPE, text=True)
    try:
        wait_until_serving(f"http://127.0.0.1:{port}/api/schema/scene")
        with socket.create_connection(("127.0.0.1", port)) as listener:
            listener.sendall(b"GET /live/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert listener.recv(64).startswith(b"HTTP/1.1 200")
            started = time.monotonic()
            server.terminate()
            server.wait(timeout=30)
            assert time.monotonic() - started < 10
        assert "Traceback" not in server.stderr.read()
    finally:
        server.kill()
        MongoClient(mongo_uri).drop_database("pmem_test_serve_stops")


@pytest.mark.parametrize("options, words", [
    (["--after", "yesterday"], "after: expected nanoseconds since the epoch or an ISO 8601"),
    (["--box", "1,2"], "box: expected a box x0,y0,z0,x1,y1,z1"),
    (["--limit", "0"], "limit=0 asks for no page: with count=true it asks for the count"),
    (["--limit", "-1"], "limit: Input should be greater than or equal to 0"),
    (["--sphere", "0,0,0", "--limit", "x"], "sphere: "),
])
def test_bad_query_options_are_one_line_naming_the_option(mongo_uri, db_name, options, words):
    line = error_line(pmem("query", "clusters", *options, MONGODB_URI=mongo_uri, PMEM_DB=db_name))
    assert words in line and "errors.pydantic.dev" not in line


def test_export_to_a_missing_folder_or_over_a_file_is_one_line(mongo_uri, db_name, tmp_path):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    missing = tmp_path / "missing" / "x.zip"
    line = error_line(pmem("export", "jsonl", "--out", str(missing), **env))
    assert f"cannot write {missing}: No such file or directory" in line
    (tmp_path / "taken.zip").write_bytes(b"keep me")
    assert "exists: an export never writes over it" in error_line(
        pmem("export", "jsonl", "--out", str(tmp_path / "taken.zip"), **env))
    assert (tmp_path / "taken.zip").read_bytes() == b"keep me"
    (tmp_path / "taken").write_text("keep me")
    assert "exists and is not an empty folder" in error_line(
        pmem("export", "jsonl", "--out", str(tmp_path / "taken"), **env))


def test_an_unreachable_robosherlock_uri_is_one_line_within_seconds(mongo_uri, db_name):
    started = time.monotonic()
    line = error_line(pmem("import", "robosherlock", "--uri", f"mongodb://127.0.0.1:{free_port()}",
                           "--db", "rs", MONGODB_URI=mongo_uri, PMEM_DB=db_name))
    assert "cannot read the RoboSherlock database at mongodb://127.0.0.1:" in line
    assert time.monotonic() - started < 20


def scene_line(seed: int) -> str:
    scene = synthetic.scene(np.random.default_rng(seed), 7_000 + seed, 1)
    return scene.model_dump_json(by_alias=True)


@pytest.mark.parametrize("name, write, words", [
    ("UTF-16", lambda path: path.write_text(scene_line(1), encoding="utf-16"),
     "scene.json: (scene): is not UTF-8 text"),
    ("Latin-1", lambda path: path.write_bytes('{"robot": "Jürgen"}'.encode("latin-1")),
     "scene.json: (scene): is not UTF-8 text"),
    ("a FIFO", lambda path: os.mkfifo(path), "scene.json: (scene): is not a regular file"),
])
def test_scene_files_that_cannot_be_read_are_named(mongo_uri, db_name, tmp_path, name, write,
                                                   words):
    write(tmp_path / "scene.json")
    line = error_line(pmem("import", "scene-log", str(tmp_path), MONGODB_URI=mongo_uri,
                           PMEM_DB=db_name))
    assert words in line


def test_a_zero_byte_image_file_is_named(mongo_uri, db_name, tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "crop.png").write_bytes(b"")
    scene = json.loads(scene_line(2))
    scene["clusters"][0]["hypotheses"][0]["crop"] = {"path": "images/crop.png"}
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    line = error_line(pmem("import", "scene-log", str(tmp_path), MONGODB_URI=mongo_uri,
                           PMEM_DB=db_name))
    assert "clusters.0.hypotheses.0.crop: the image file 'images/crop.png' is empty" in line


def test_an_import_stopped_by_a_bad_line_says_what_it_stored(mongo_uri, db_name, tmp_path,
                                                             store):
    lines = [scene_line(100 + i) for i in range(45)]
    lines[40] = '{"robot": "pr2"}'
    (tmp_path / "log.jsonl").write_text("\n".join(lines) + "\n")
    line = error_line(pmem("import", "scene-log", str(tmp_path), MONGODB_URI=mongo_uri,
                           PMEM_DB=db_name))
    assert "log.jsonl:41: timestamp: Field required" in line
    # the batches of 32 before line 41's: not "before line 41", lines 33-40 are not stored
    assert "Stored: the first 32 scenes read (32 new; importing again skips them), none " \
           "after them" in line
    stored = store.scenes.count_documents({"timestamp": {"$gte": 7_100, "$lt": 7_145}})
    assert stored == 32


@pytest.mark.parametrize("files", [{"a.json": "[]"}, {"a.jsonl": "\n  \n"}])
def test_an_import_of_no_scene_is_an_error(mongo_uri, db_name, tmp_path, files):
    """It printed "0 new scenes, 0 stored before" and exited 0."""
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    line = error_line(pmem("import", "scene-log", str(tmp_path), MONGODB_URI=mongo_uri,
                           PMEM_DB=db_name))
    assert line == f"Error: {tmp_path.name}: no scene in it; nothing imported"


def test_index_adds_lists_and_drops_a_field_index_and_says_when_it_did_nothing(
        mongo_uri, db_name, store):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    store.drop_field_index("class_name")
    added = pmem("index", "add", "classification:class_name", **env)
    assert added.exit_code == 0, added.output
    assert "indexed class_name" in added.output
    assert "class_name" in pmem("index", **env).output.splitlines()
    again = pmem("index", "add", "detection:name", **env)  # another field: its own index
    assert again.exit_code == 0 and "name" in store.field_indexes()
    twice = pmem("index", "add", "classification:class_name", **env)
    assert twice.exit_code == 1 and twice.output == "Error: class_name has an index already\n"
    for bad, said in (("colorhistogram:histogram", "not a scalar field"),
                      ("classification", "expected type:field")):
        refused = pmem("index", "add", bad, **env)
        assert refused.exit_code == 1 and said in refused.output, refused.output
        assert "Traceback" not in refused.output
    assert pmem("index", "drop", "classification:class_name", **env).exit_code == 0
    assert pmem("index", "drop", "detection:name", **env).exit_code == 0
    gone = pmem("index", "drop", "classification:class_name", **env)
    assert gone.exit_code == 1 and "has no index" in gone.output
    assert store.field_indexes() == []


def test_the_served_socket_turns_nagle_off_for_each_connection():
    """pmem serve binds its socket itself; asyncio (under uvicorn) turns off Nagle's algorithm
    only on connections of a socket that says it is TCP. With it on, a response on a kept-alive
    connection waited ~40 ms for the client's delayed ACK, every request (bench/belief.py's
    HTTP time per scene went from 24 to 67 ms p50)."""
    import asyncio

    from percept_memory.cli import listening

    async def accepted_nodelay() -> int:
        loop = asyncio.get_running_loop()
        made: asyncio.Future = loop.create_future()

        class Probe(asyncio.Protocol):
            def connection_made(self, transport):
                made.set_result(transport.get_extra_info("socket").getsockopt(
                    socket.IPPROTO_TCP, socket.TCP_NODELAY))
                transport.close()

        sock = listening("127.0.0.1", 0)
        server = await loop.create_server(Probe, sock=sock)
        _, writer = await asyncio.open_connection(*sock.getsockname()[:2])
        try:
            return await asyncio.wait_for(made, 10)
        finally:
            writer.close()
            server.close()

    assert asyncio.run(accepted_nodelay()) != 0


def test_a_far_coordinate_is_printed_short():
    """Any finite coordinate is stored (UTM, or 1e300); a table printed 1e300 with 300 digits."""
    from percept_memory.answers import cell

    assert [cell(v) for v in (1e300, -2.5e7, 455_000.1234, 0.5)] == [
        "1e+300", "-2.5e+07", "455000.123", "0.5"]
