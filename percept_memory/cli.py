"""`pmem`, the command line of percept-memory: one click group, one section per subcommand.

Results go to stdout (so `export MONGODB_URI=$(pmem db start)` works); progress, warnings and
errors go to stderr. Expected failures print `Error: <what happened and what to do>` and exit
with code 1, never a traceback.

Conventions: what a command is about is its argument (a query's subject X, an import's folder,
an export's format); where and when are options (`--region`, `--t`, `--after`); `--json`
prints for scripts, else text for people; every command's help ends with an example. Modules
are imported by the commands that use them, so that `pmem --help` and `pmem query` start fast
(FastAPI, OpenCV and the demo's generator are not loaded for them).
"""

from __future__ import annotations

import gc
import json
import logging
import os
import signal
import socket
from pathlib import Path
from typing import Any

import click
from pydantic import ValidationError

from percept_memory.answers import printable
from percept_memory.ingest.errors import BackendSetupError, IngestError, SourceError
from percept_memory.memory.errors import StoreError, problems_line, redacted
from percept_memory.memory.mongod import EmbeddedMongod, EmbeddedMongoError
from percept_memory.memory.settings import (
    Settings,
    collect_less,
    settings_help,
    settings_problems,
)
from percept_memory.memory.types.modules import TypeModuleError

HELP = f"""percept-memory: a long-term spatio-temporal memory for robot perception.

Settings come from these environment variables:

\b
  PMEM_SHARED_DATA: the RoboSherlock data `pmem demo` loads (default: shared/data/robosherlock
  beside the checkout)
{settings_help()}"""


def example(*lines: str) -> str:
    """A command's help epilog: how it is used (\\b keeps click from re-wrapping the lines)."""
    heading = "Example:" if len(lines) == 1 else "Examples:"
    return f"\b\n{heading}\n" + "\n".join(f"  {line}" for line in lines)


class _Group(click.Group):
    """The top-level group: turns our expected failures into click's `Error: ...` exit, and a
    command line click cannot parse too (its own form is a usage, a hint, a blank line and the
    error, exit 2): every failure of pmem is one line `Error: ...` and exit 1."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except (EmbeddedMongoError, StoreError, IngestError, SourceError, ValidationError,
                BackendSetupError, TypeModuleError) as exc:
            raise click.ClickException(one_line(exc)) from exc
        except click.UsageError as exc:  # (a subcommand's options and arguments)
            hint = f" (see `{exc.ctx.command_path} --help`)" if exc.ctx else ""
            raise click.ClickException(exc.format_message() + hint) from exc


def one_line(error: Exception) -> str:
    """An error as one line: pydantic's as `field: problem; ...` (no input echoed, no URL)."""
    if isinstance(error, ValidationError):
        return printable(problems_line(error))
    return printable(" ".join(str(error).split()))


class _StderrHandler(logging.Handler):
    """Shows the library's progress and warnings on whatever stderr is at the time of the call."""

    def emit(self, record: logging.LogRecord) -> None:
        prefix = f"{record.levelname.capitalize()}: " if record.levelno >= logging.WARNING else ""
        click.echo(prefix + record.getMessage(), err=True)


@click.group(cls=_Group, help=HELP, epilog=example(
    "pmem demo", 'pmem query where-is "the ketchup"', "pmem COMMAND --help"))
@click.pass_context
def main(ctx: click.Context) -> None:
    collect_less()
    logger = logging.getLogger("percept_memory")
    logger.handlers = [_StderrHandler()]
    logger.setLevel(logging.INFO)
    try:
        ctx.obj = Settings()
    except ValidationError as error:
        raise click.ClickException(settings_problems(error)) from None


# --- pmem db: the embedded mongod --------------------------------------------------------------


@main.group(epilog=example("pmem db status"))
def db() -> None:
    """Manage the embedded local mongod, used when MONGODB_URI is unset."""


def _external_database(settings: Settings) -> bool:
    """True (and says so) when MONGODB_URI points elsewhere, so there is nothing to manage."""
    if settings.mongodb_uri:
        click.echo(
            "MONGODB_URI is set: percept-memory uses that external database and does not "
            "manage it. Nothing to do.",
            err=True,
        )
    return bool(settings.mongodb_uri)


@db.command(epilog=example("export MONGODB_URI=$(pmem db start)"))
@click.pass_obj
def start(settings: Settings) -> None:
    """Start the embedded mongod (or reuse the running one) and print its URI."""
    if not _external_database(settings):
        click.echo(EmbeddedMongod.from_settings(settings).start())


@db.command(epilog=example("pmem db stop"))
@click.pass_obj
def stop(settings: Settings) -> None:
    """Shut the embedded mongod down cleanly."""
    if not _external_database(settings):
        EmbeddedMongod.from_settings(settings).stop()


@db.command(epilog=example("pmem db status --json"))
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON.")
@click.pass_obj
def status(settings: Settings, as_json: bool) -> None:
    """Show whether the embedded mongod runs, where, and how much disk it uses."""
    if settings.mongodb_uri:
        click.echo("Note: MONGODB_URI is set, so percept-memory does not use this one.", err=True)
    info = EmbeddedMongod.from_settings(settings).status()
    if as_json:
        click.echo(json.dumps(info, indent=2))
        return
    for key, value in info.items():
        shown = "size" if key == "size_bytes" else key  # (in MiB: not its bytes)
        click.echo(f"{shown + ':':<12}{_readable(key, value)}")


def _readable(key: str, value: Any) -> str:
    if value is None:
        return "-"
    if key == "running":
        return "yes" if value else "no"
    if key == "size_bytes":
        return f"{value / 2**20:.1f} MiB"
    return str(value)


# --- pmem info: what the memory holds ------------------------------------------------------------


@main.command(epilog=example("pmem info", "PMEM_DB=scratch pmem info --json"))
@click.option("--json", "as_json", is_flag=True, help="Print the counts as JSON.")
@click.pass_obj
def info(settings: Settings, as_json: bool) -> None:
    """Show the database in use and how many documents and annotations of each type it holds."""
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        report = {
            "database": settings.db,
            "uri": redacted(settings.mongodb_uri) if settings.mongodb_uri else "embedded",
            **store.counts(),
        }
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    click.echo(f"database:   {report['database']} ({report['uri']})")
    for heading, counts in (("collections", report["collections"]), ("types", report["types"])):
        click.echo(f"{heading}:")
        width = max((len(name) for name in counts), default=0)
        for name, count in counts.items():
            click.echo(f"  {name:<{width}}  {count:>9,}")
    if not report["types"]:
        click.echo("  (no annotations stored yet)")


def progress_bar(label: str):
    """The bar long operations show on stderr (stdout stays for their results), when it is a
    terminal."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
    )

    console = Console(stderr=True)
    # (not drawn where stderr is no terminal: a log or a pipe would get its last line, or an
    # empty one before an error)
    return Progress(TextColumn(f"[bold]{label}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=console, transient=True,
                    disable=not console.is_terminal)


# --- pmem import: bring percepts in -----------------------------------------------------------


def ingest_with_progress(store, source: str, items, context: dict | None = None):
    """Feed (label, scene) items through the ingest service with a progress bar on stderr,
    the memory pipeline consolidating them meanwhile; returns the ImportSummary once their
    belief is current."""
    from percept_memory.ingest.service import ImportSummary, IngestService, memory_pipeline

    summary = ImportSummary()
    pipeline = memory_pipeline(store).start()
    try:
        with progress_bar(source) as progress:
            task = progress.add_task(source, total=None)
            service = IngestService(store, pipeline=pipeline)
            try:
                for ingested in service.ingest_stream(items, context):
                    summary.add(ingested)
                    progress.advance(task)
            except IngestError as error:  # never a silent partial import (a batch is
                # stored whole or not at all: the scenes of the bad one before it are not)
                stored = summary.scenes_new + summary.scenes_existing
                raise click.ClickException(
                    f"{one_line(error)}. Stored: the first {stored} "
                    f"{_plural(stored, 'scene')} read ({summary.scenes_new} new; importing "
                    "again skips them), none after them") from None
    finally:
        pipeline.stop()
    if not summary.scenes_new + summary.scenes_existing:
        raise click.ClickException(f"{source}: no scene in it; nothing imported")
    drain_with_progress(store, pipeline)
    return summary


def drain_with_progress(store, pipeline) -> None:
    """Run the pipeline until no scene is pending, with a progress bar on stderr."""
    with progress_bar("belief") as bar:
        task = bar.add_task("scenes", total=pipeline.pending())
        pipeline.drain(progress=lambda done: bar.advance(task, done))


def echo_summary(source: str, summary) -> None:
    click.echo(f"{source}: {summary.scenes_new} new {_plural(summary.scenes_new, 'scene')}, "
               f"{summary.scenes_existing} stored before, {summary.clusters} clusters")
    for name, count in sorted(summary.types.items()):
        click.echo(f"  {name:<36} {count:>8,}")


def _plural(count: int, word: str) -> str:
    return word if count == 1 else word + "s"


def labelled(source: str, scenes):
    return ((f"{source} scene at {scene.timestamp}", scene) for scene in scenes)


@main.group(name="import", epilog=example("pmem import scene-log recordings/"))
def import_() -> None:
    """Bring percepts into the memory (scenes already stored are not duplicated)."""


@import_.command(name="scene-log", epilog=example("pmem import scene-log recordings/"))
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.pass_obj
def import_scene_log(settings: Settings, folder: Path) -> None:
    """A folder of scenes in the interchange format v1 (see `pmem schema`)."""
    from percept_memory.ingest.scene_log import read_scene_log
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        summary = ingest_with_progress(store, folder.name, read_scene_log(folder),
                                       {"folder": folder})
    echo_summary(str(folder), summary)


@import_.command(name="robosherlock", epilog=example(
    "pmem import robosherlock ../shared/data/robosherlock/mongodump/IJRRScenes",
    "pmem import robosherlock --uri mongodb://robot:27017 --db PnP09 --map lab"))
@click.argument("folder", required=False,
                type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--uri", help="a live RoboSherlock MongoDB instead of a mongodump folder")
@click.option("--db", "database", help="the RoboSherlock database name (with --uri)")
@click.option("--robot", default="pr2", show_default=True, help="robot the data came from")
@click.option("--map", "map_name", help="the map the scenes belong to  "
              "[default: robosherlock/<folder or db name>]")
@click.pass_obj
def import_robosherlock(settings: Settings, folder: Path | None, uri: str | None,
                        database: str | None, robot: str, map_name: str | None) -> None:
    """RoboSherlock's storage: a mongodump FOLDER, or a live database (--uri and --db)."""
    from percept_memory.ingest import robosherlock
    from percept_memory.memory.store import MemoryStore

    if (folder is None) == (uri is None) or (uri is not None and not database):
        raise click.UsageError("give a mongodump FOLDER, or --uri and --db")
    scenes = robosherlock.read_dump(folder, robot, map_name) if folder else \
        robosherlock.read_database(uri, database, robot, map_name)
    source = folder.name if folder else f"{database}@{redacted(uri)}"
    with MemoryStore.open(settings) as store:
        summary = ingest_with_progress(store, source, labelled(source, scenes))
    echo_summary(source, summary)


def _iso_time(_ctx, _param, value: str | None) -> int | None:
    """An ISO 8601 time (naive is UTC) as nanoseconds since the epoch."""
    from percept_memory.memory.types import timestamp_from_iso

    try:
        return None if value is None else timestamp_from_iso(value)
    except ValueError:
        raise click.BadParameter(f"expected an ISO 8601 time such as 2018-03-28T15:13:07Z, "
                                 f"got {value!r}") from None


@import_.command(name="rgbd", epilog=example(
    "pmem import rgbd ../shared/data/robosherlock/samples/kitchen --robot kinect --map lab"))
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--robot", default="pr2", show_default=True, help="robot the data came from")
@click.option("--map", "map_name", help="the map the scenes belong to  [default: rgbd/<folder>]")
@click.option("--time", "start", metavar="ISO", callback=_iso_time,
              help="when the samples that record no time (PCD + image) were taken, the next "
              "ones a second apart  [default: their cloud files' modification times]")
@click.pass_obj
def import_rgbd(settings: Settings, folder: Path, robot: str, map_name: str | None,
                start: int | None) -> None:
    """RGB-D samples: PNG + depth PNG + viewpoint, PNG + PCD (+ ground-truth .lbl), or
    RoboSherlock's test_rgb_image + test_point_cloud + test_viewpoint."""
    from percept_memory.ingest import rgbd
    from percept_memory.memory.store import MemoryStore

    scenes = rgbd.read_samples(folder, robot, map_name, start)
    with MemoryStore.open(settings) as store:
        summary = ingest_with_progress(store, folder.name, labelled(folder.name, scenes))
    echo_summary(str(folder), summary)
    times = ", ".join(f"{count} from {how}" for how, count in sorted(scenes.times.items()))
    click.echo(f"scene times: {times}")


@main.command(epilog=example("pmem schema > scene.schema.json"))
def schema() -> None:
    """Print the JSON Schema of a scene (interchange format v1)."""
    from percept_memory.memory.types import Scene

    click.echo(json.dumps(Scene.model_json_schema(), indent=2))


# --- pmem serve / pmem demo -------------------------------------------------------------------


def listening(host: str, port: int) -> socket.socket:
    """A socket bound to host:port for the web app, or the one-line error saying why not (a
    port in use, a host that is not this machine's): taken before anything is loaded."""
    try:  # (the family as uvicorn picks it: "localhost" is 127.0.0.1, not ::1; TCP named,
        # or asyncio leaves Nagle on for its connections: a kept-alive connection's response
        # then waited ~40 ms for the client's delayed ACK, each request)
        sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET,
                             socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
    except OSError as error:
        raise click.ClickException(
            f"cannot listen on {host}:{port}: {error.strerror or error}") from None
    return sock


def serve_app(store, settings: Settings, host: str, sock: socket.socket) -> None:
    """The web app and the HTTP API on the socket (bound to `host`) until Ctrl-C."""
    import uvicorn

    from percept_memory.webui.app import create_app
    from percept_memory.webui.guard import served_settings

    app = create_app(store, served_settings(settings, host))
    # What is loaded now lives as long as the server: out of the collector's way, so that
    # each full collection (a request body parses into ~100,000 objects) skips it (-10 % CPU).
    gc.freeze()
    # stopping, open streams (the live page's events, an export a client stopped reading)
    # get SHUTDOWN_S to end, then are cut: they kept the server up as long as they lasted
    uvicorn.Server(uvicorn.Config(app, log_level="warning",
                                  timeout_graceful_shutdown=SHUTDOWN_S)).run(sockets=[sock])


SHUTDOWN_S = 5


PORT = click.IntRange(1, 65535)


@main.command(epilog=example("pmem serve --port 8080"))
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=8000, show_default=True, type=PORT)
@click.pass_obj
def serve(settings: Settings, host: str, port: int) -> None:
    """Run the web app and the HTTP API (OpenAPI at /docs)."""
    from percept_memory.memory.store import MemoryStore

    sock = listening(host, port)
    with MemoryStore.open(settings) as store:
        click.echo(f"percept-memory at http://{host}:{port}/docs", err=True)
        serve_app(store, settings, host, sock)


@main.command(epilog=example("pmem demo", "PMEM_DB=scratch pmem demo --no-serve --workers 0"))
@click.option("--days", default=7, show_default=True, type=click.IntRange(0),
              help="days of the generated kitchen week (0: none)")
@click.option("--serve/--no-serve", "serving", default=True, show_default=True,
              help="serve the web app once the data is in")
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=8000, show_default=True, type=PORT)
@click.option("--workers", default=1, show_default=True, type=click.IntRange(0),
              help="enrichment worker processes looking the clusters up (0: none)")
@click.option("--backend", default="simulated", show_default=True,
              type=click.Choice(["simulated", "catalogue"]), help="what the workers ask")
@click.pass_obj
def demo(settings: Settings, days: int, serving: bool, host: str, port: int, workers: int,
         backend: str) -> None:
    """The demo: the embedded database with the real RoboSherlock data and a generated kitchen
    week, enrichment workers appending lookup results to the clusters as they come in, then
    the web app (with --no-serve: until the lookups are done). Running it again adds nothing
    that is there already."""
    from percept_memory.ingest.workers import worker_processes
    from percept_memory.memory.store import MemoryStore

    sock = listening(host, port) if serving else None
    with MemoryStore.open(settings) as store, worker_processes(workers, backend) as running:
        for source, scenes in demo_sources(days):
            echo_summary(source, ingest_with_progress(store, source, labelled(source, scenes)))
        if sock is not None:
            click.echo(f"percept-memory demo at http://{host}:{port}/docs  (Ctrl-C stops)")
            serve_app(store, settings, host, sock)
        elif running:
            counts = wait_for_lookups(store, running)
            click.echo(f"lookups: {counts['done']} done, {counts['failed']} failed")


def wait_for_lookups(store, workers: list) -> dict[str, int]:
    """Jobs per state once none is queued or running, with a progress bar on stderr."""
    import time

    from percept_memory.ingest.jobs import job_report

    with progress_bar("lookups") as bar:
        task = bar.add_task("lookups", total=None)
        while True:
            counts = job_report(store, limit=0)["counts"]
            bar.update(task, total=sum(counts.values()),
                       completed=counts["done"] + counts["failed"])
            if not counts["queued"] + counts["running"]:
                return counts
            if all(worker.poll() is not None for worker in workers):
                raise click.ClickException("the lookup workers stopped; see their errors above")
            time.sleep(0.5)


# The demo's RGB-D samples that record no time are put at this one (a second apart), not at
# their files' modification times: a fresh clone or a copy of the data has new ones, and the
# demo run again stored them again.
DEMO_SAMPLES_TIME = 1_522_238_400_000_000_000  # 2018-03-28T12:00:00Z, the samples' day


def demo_sources(days: int):
    """(name, scenes) of everything the demo loads: real data first, then the kitchen week."""
    from percept_memory.demo import kitchen_week
    from percept_memory.ingest import rgbd, robosherlock

    data = shared_data_dir()
    for folder in sorted((data / "samples").iterdir()):  # (at a time of their own: see below)
        yield f"samples/{folder.name}", rgbd.read_samples(folder, time=DEMO_SAMPLES_TIME)
    for folder in sorted((data / "mongodump").iterdir()):
        yield f"mongodump/{folder.name}", robosherlock.read_dump(folder)
    if days:
        yield f"kitchen week ({days} days)", kitchen_week.generate(days=days).scenes


def shared_data_dir() -> Path:
    """The real RoboSherlock data: PMEM_SHARED_DATA, else shared/data/robosherlock beside the
    checkout."""
    configured = os.environ.get("PMEM_SHARED_DATA")
    folder = Path(configured) if configured else (
        Path(__file__).resolve().parents[2] / "shared" / "data" / "robosherlock")
    if not folder.is_dir():
        raise click.ClickException(
            f"no RoboSherlock data at {folder}: set PMEM_SHARED_DATA to the robosherlock folder")
    return folder


# --- pmem worker / pmem jobs: enrichment ---------------------------------------------------------


@main.command(epilog=example("pmem worker --backend catalogue --concurrency 8"))
@click.option("--backend", type=click.Choice(["simulated", "catalogue", "http"]),
              help="the lookup backend  [default: PMEM_LOOKUP_BACKEND]")
@click.option("--concurrency", type=click.IntRange(1),
              help="lookups in flight  [default: PMEM_LOOKUP_CONCURRENCY]")
@click.option("--nice", default=10, show_default=True, type=click.IntRange(0, 19),
              help="lower CPU priority, so ingest on the same machine comes first")
@click.pass_obj
def worker(settings: Settings, backend: str | None, concurrency: int | None, nice: int) -> None:
    """Run lookup jobs until SIGTERM or Ctrl-C: each new cluster's crop is looked up (the
    shared pHash cache first) and the results appended to it. Start as many as you like, on
    any machine: they share the queue through leases."""
    import asyncio

    from percept_memory.ingest.workers import run_worker

    os.nice(nice)
    counts = asyncio.run(run_worker(settings, backend=backend, concurrency=concurrency))
    click.echo(f"worker stopped: {counts['done']} jobs done ({counts['cached']} from the cache), "
               f"{counts['retried']} to retry, {counts['failed']} failed, "
               f"{counts['released']} released", err=True)


JOB_STATES = ("queued", "running", "done", "failed")  # ingest/jobs.py: STATES


@main.command(epilog=example("pmem jobs --state failed --limit 5", "pmem jobs --retry-failed"))
@click.option("--state", type=click.Choice(JOB_STATES), help="list only jobs in this state")
@click.option("--limit", default=20, show_default=True, type=click.IntRange(0),
              help="how many of the latest jobs to list")
@click.option("--retry-failed", is_flag=True, help="queue the failed jobs again first")
@click.option("--json", "as_json", is_flag=True, help="print the report as JSON")
@click.pass_obj
def jobs(settings: Settings, state: str | None, limit: int, retry_failed: bool,
         as_json: bool) -> None:
    """The enrichment queue: jobs per state, and the latest jobs with their last error."""
    from percept_memory.ingest.jobs import job_report, requeue_failed
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        if retry_failed:  # (then the report, what the command is for)
            queued = requeue_failed(store)
            click.echo(f"{queued} failed job(s) queued again" if queued else
                       "no failed job to queue again", err=True)
        report = job_report(store, state, limit)
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    click.echo("  ".join(f"{name}: {count:,}" for name, count in report["counts"].items()))
    for job in report["jobs"]:
        detail = job.get("error") if job["state"] != "done" else _outcome(job.get("outcome", {}))
        click.echo(f"{job['id']}  {job['state']:<7} attempts {job['attempts']}  "
                   f"{job['updated'][:19]}  {printable(detail or '')}")


def _outcome(outcome: dict) -> str:
    how = f"cached, {outcome['hash_distance']} bits off" if outcome.get("cached") else "fresh"
    return f"{outcome.get('annotations', 0)} annotations ({outcome.get('backend')}, {how})"


@main.command(epilog=example("pmem reconsolidate"))
@click.pass_obj
def reconsolidate(settings: Settings) -> None:
    """Rebuild every map's objects and events from its stored scenes, in time order (after a
    change of the identity parameters): the same code as the live pipeline, so the same store
    always gives the same belief."""
    from percept_memory.ingest.service import memory_pipeline
    from percept_memory.memory.pipeline import request_rebuild
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        maps = request_rebuild(store)
        if not maps:
            raise click.ClickException(f"no scene to reconsolidate in database {settings.db}")
        drain_with_progress(store, memory_pipeline(store, settings))
        objects = store.db["objects"].count_documents({})
        events = store.db["events"].count_documents({})
        scenes = store.scenes.estimated_document_count()
    click.echo(f"reconsolidated {scenes} scenes in {len(maps)} {_plural(len(maps), 'map')}: "
               f"{objects} objects, {events} events")


@main.command(name="pipeline", epilog=example("pmem pipeline", "pmem pipeline --retry --json"))
@click.option("--retry", is_flag=True, help="queue the held scenes again")
@click.option("--json", "as_json", is_flag=True, help="print the report as JSON")
@click.pass_obj
def pipeline_report(settings: Settings, retry: bool, as_json: bool) -> None:
    """How far each map's belief is: the newest consolidated scene, the scenes pending and
    held (a stage kept failing: their errors are listed), and who consolidates it."""
    from percept_memory.memory.pipeline import retry_held
    from percept_memory.memory.pipeline import status as pipeline_status
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        if retry:  # (then the report, what the command is for)
            queued = retry_held(store)
            click.echo(f"{queued} held scene(s) queued again" if queued else
                       "no held scene to retry", err=True)
        report = pipeline_status(store)
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    if not report["maps"]:
        click.echo("no scene is stored yet: no map to consolidate", err=True)
    width = max((len(row["map"]) for row in report["maps"]), default=0)
    for row in report["maps"]:
        until = row["consolidated_until"] or "-"
        click.echo(f"{printable(row['map']):<{width}}  consolidated until {until:<30} "
                   f"pending {row['pending']:>6}  held {row['held']:>4}"
                   f"{'  rebuilding' if row['rebuilding'] else ''}"
                   f"{'  by ' + row['consolidator'] if row['consolidator'] else ''}")
    for held in report["held"]:
        click.echo(printable(f"held: scene {held['scene_id']} ({held['map']}, {held['time']}), "
                             f"{held['attempts']} attempts: {held['error']}"))


@main.command(epilog=example("PMEM_CONSOLIDATOR=false pmem serve &  pmem consolidate"))
@click.pass_obj
def consolidate(settings: Settings) -> None:
    """Run the memory pipeline until SIGTERM or Ctrl-C: consolidate stored scenes into the
    belief and queue their lookups. For deployments that run it apart from the web app
    (PMEM_CONSOLIDATOR=false); as many as you like: each map has one writer at a time."""
    import signal

    from percept_memory.ingest.service import memory_pipeline
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        pipeline = memory_pipeline(store, settings)
        for stopping in (signal.SIGTERM, signal.SIGINT):
            signal.signal(stopping, lambda *_: pipeline.stop_soon())
        click.echo("consolidating: SIGTERM or Ctrl-C stops", err=True)
        pipeline.run_forever()
    click.echo("consolidator stopped", err=True)


@main.group(invoke_without_command=True, epilog=example(
    "pmem index", "pmem index add classification:confidence"))
@click.pass_context
def index(ctx: click.Context) -> None:
    """List the annotation fields with an index of their own (add or drop one: one index serves
    the field of that name of every type). Text, labels,
    names, regions, robots, objects, time and places are always indexed; a predicate on any
    other field (--where classification:confidence>0.8) is fast when the query is narrowed by
    those, or when its field has an index."""
    if ctx.invoked_subcommand is not None:
        return
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(ctx.obj) as store:
        fields = store.field_indexes()
    for field in fields:
        click.echo(field)
    if not fields:
        click.echo("no field has an index of its own: pmem index add TYPE:FIELD adds one",
                   err=True)


@index.command(name="add", epilog=example("pmem index add classification:confidence"))
@click.argument("field")
@click.pass_obj
def index_add(settings: Settings, field: str) -> None:
    """Index FIELD (type:field, as --where names it) of every cluster's annotations."""
    _change_field_index(settings, field, add=True)


@index.command(name="drop", epilog=example("pmem index drop classification:confidence"))
@click.argument("field")
@click.pass_obj
def index_drop(settings: Settings, field: str) -> None:
    """Drop the index of FIELD added before."""
    _change_field_index(settings, field, add=False)


def _change_field_index(settings: Settings, field: str, add: bool) -> None:
    from percept_memory.memory.store import MemoryStore
    from percept_memory.queries.model import annotation_field

    try:
        _, path = annotation_field(field)
    except ValueError as error:
        raise click.ClickException(str(error)) from None
    with MemoryStore.open(settings) as store:
        if add and path in store.field_indexes():
            raise click.ClickException(f"{path} has an index already")
        if add:
            click.echo(f"indexing the annotations' {path} over "
                       f"{store.clusters.estimated_document_count()} clusters...", err=True)
            changed = store.add_field_index(path)
        else:
            changed = store.drop_field_index(path)
    if not changed:
        raise click.ClickException(f"{path} {'has an index already' if add else 'has no index'}")
    click.echo(f"{'indexed' if add else 'dropped the index of'} {path} (the field of that name "
               "of every annotation type)")


@main.command(epilog=example("pmem reindex"))
@click.pass_obj
def reindex(settings: Settings) -> None:
    """Recompute the search keys, scene summaries and vocabulary of everything stored (after
    an upgrade that changed them; the stored percepts themselves are not touched)."""
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        total = (store.clusters.estimated_document_count()
                 + store.scenes.estimated_document_count())
        with progress_bar("reindex") as bar:
            task = bar.add_task("clusters and scenes", total=total)
            count = store.reindex(lambda: bar.advance(task))
    if not count:
        raise click.ClickException("nothing to reindex: no cluster is stored")
    click.echo(f"reindexed {count} clusters")


# --- pmem query: the query API on the command line -------------------------------------------

SUBJECTS = ("x", "format")  # the fields that are a command's argument: what it is about
EXAMPLES = {
    "clusters": ("pmem query clusters --text cereal --region shelf --limit 5",
                 'pmem query clusters --text "something to drink" --meaning --limit 5',
                 "pmem query clusters --near 1.9,4.6,0.8 --k 3 --json"),
    "where_is": ('pmem query where-is "the ketchup" --limit 1',),
    "where_was": ("pmem query where-was pringles --after 2024-03-05",),
    "last_seen": ("pmem query last-seen pringles",),
    "what_is_at": ("pmem query what-is-at --map kitchen-week --region table "
                   "--t 2024-03-06T08:30",),
    "changes": ("pmem query changes --region table --t1 2024-03-06T07:00 "
                "--t2 2024-03-06T10:00",),
    "annotation_stats": ("pmem query annotation-stats --region shelf",),
    "cooccurrence": ("pmem query cooccurrence pringles --by-hour",),
    "timings": ("pmem query timings --robot pr2 --json",),
    "playback": ("pmem query playback --robot pr2 --t 2024-03-06T08:30 --step next",),
    "annotator_report": ("pmem query annotator-report --robot pr2 --scenes 100 --json",),
    "annotator_clusters": ('pmem query annotator-clusters --robot pr2 --annotator '
                           'DeCafClassifier --reference "(ground truth)" --said SiggBottle '
                           '--expected SiggBottle',),
}


class _Queries(click.Group):
    """`pmem query`: one subcommand per query of the engine, made from its model when asked
    for, so that commands which ask nothing do not import the query engine."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        from percept_memory.queries.engine import QUERIES

        return [*(name.replace("_", "-") for name in QUERIES), "similar",
                *super().list_commands(ctx)]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        from percept_memory.queries.engine import QUERIES

        if cmd_name == "similar":
            from percept_memory.cli_similar import similar_command

            return similar_command()
        name = cmd_name.replace("-", "_")
        if name in QUERIES:
            return _query_command(name, QUERIES[name][0])
        return super().get_command(ctx, cmd_name)  # those of the long-term catalogue


@main.group(cls=_Queries, epilog=example('pmem query where-is "the ketchup"'))
def query() -> None:
    """Ask the memory: clusters (text, space, time, annotation fields), where-is, where-was,
    last-seen, what-is-at, changes, stats. The subject (X) is the argument; places and times
    are options, those of the HTTP API's query string (see /docs); times are ISO 8601 (UTC)
    or nanoseconds. Prints text for people, or JSON with --json."""


def model_params(model) -> list[click.Parameter]:
    """A model's fields as options (the subject as an argument), to be read by the same
    parser as the HTTP query string (model_from_options)."""
    from percept_memory.queries.params import is_list

    params: list[click.Parameter] = []
    for field, info in model.model_fields.items():
        if field in SUBJECTS:
            params.append(click.Argument([field], required=info.is_required()))
        elif info.annotation is bool:
            params.append(click.Option([f"--{field.replace('_', '-')}"], is_flag=True,
                                       default=None, help=info.description))
        else:
            params.append(click.Option([f"--{field.replace('_', '-')}", field],
                                       required=info.is_required(),
                                       multiple=is_list(model, field), help=info.description))
    return params


def model_from_options(model, given: dict[str, Any]):
    from percept_memory.queries.params import from_params

    pairs = [(field, str(value).lower() if isinstance(value, bool) else str(value))
             for field, values in given.items() if values is not None
             for value in (values if isinstance(values, tuple) else (values,))]
    return from_params(model, pairs)


def _query_command(name: str, model) -> click.Command:
    """A subcommand whose parameters are the query model's fields, read by the same parser
    as the HTTP query string."""
    from percept_memory.queries.engine import QUERIES

    @click.pass_obj
    def run(settings: Settings, as_json: bool, **given: Any) -> None:
        from percept_memory import answers
        from percept_memory.memory.store import MemoryStore
        from percept_memory.queries.engine import QueryEngine, rebuilding_for

        question = model_from_options(model, given)
        with MemoryStore.open(settings) as store:
            rebuilt = set(rebuilding_for(store.db, name, question))
            answer = getattr(QueryEngine(store, settings), name)(question)
            rebuilt |= set(rebuilding_for(store.db, name, question))
        if rebuilt:
            click.echo(f"Warning: the belief of {', '.join(sorted(rebuilt))} is being rebuilt: "
                       "this answer holds only the scenes consolidated so far (`pmem pipeline` "
                       "shows how far)", err=True)
        if as_json:
            click.echo(answers.as_json(answer))
        elif answer == []:
            click.echo("nothing matches", err=True)
        else:
            click.echo(answers.as_text(answer))

    as_json = click.Option(["--json", "as_json"], is_flag=True,
                           help="print the answer as JSON (times as ISO 8601 and in ns)")
    return click.Command(name.replace("_", "-"), callback=run,
                         params=[*model_params(model), as_json],
                         help=(QUERIES[name][1].__doc__ or "").strip().split("\n\n")[0],
                         epilog=example(*EXAMPLES[name]))


@query.command("catalogue", epilog=example("pmem query catalogue --limit 5"))
@click.option("--map", "map_name", help="only this map's entries")
@click.option("--limit", type=click.IntRange(1, 1000), default=100, show_default=True)
@click.option("--offset", type=click.IntRange(0), default=0, show_default=True,
              help="entries skipped, the most seen")
@click.option("--json", "as_json", is_flag=True, help="print the entries as JSON")
@click.pass_obj
def catalogue_entries(settings: Settings, map_name: str | None, limit: int, offset: int,
                      as_json: bool) -> None:
    """Which objects this home has: the long-term catalogue's entries, the most seen first
    (how many of how many on stderr)."""
    from percept_memory import answers
    from percept_memory.memory.store import MemoryStore
    from percept_memory.queries import catalogue

    with MemoryStore.open(settings) as store:
        found, total = catalogue.page(store, map_name, limit, offset)
    if not total:
        raise click.ClickException("the catalogue is empty (no scene consolidated yet?)")
    if not found:
        raise click.ClickException(f"no entries after the first {total}")
    click.echo(answers.as_json(found) if as_json else "\n".join(map(catalogue.as_text, found)))
    click.echo(f"entries {offset + 1}-{offset + len(found)} of {total}", err=True)


@query.command("seen-before", epilog=example("pmem query seen-before CLUSTER_ID"))
@click.argument("cluster_id")
@click.option("--limit", type=click.IntRange(1, 100), default=5, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the entries as JSON")
@click.pass_obj
def seen_before(settings: Settings, cluster_id: str, limit: int, as_json: bool) -> None:
    """Have we seen this cluster's object before: the catalogue entries it may be, best first,
    with the share of its views each holds (inclusion) and how far its kinds of evidence
    agree (consensus)."""
    from bson import ObjectId

    from percept_memory.memory.store import MemoryStore
    from percept_memory.queries import catalogue

    if not ObjectId.is_valid(cluster_id):
        raise click.ClickException(f"{cluster_id!r} is not a cluster id (24 hex digits)")
    with MemoryStore.open(settings) as store:
        ranked = catalogue.seen_before(store, ObjectId(cluster_id), limit)
    if not ranked:
        raise click.ClickException("nothing in the catalogue looks like it")
    click.echo(json.dumps(ranked, indent=1) if as_json else "\n".join(
        f"inclusion {e['inclusion']:.2f}  consensus {e['consensus']:.2f}  {catalogue.as_text(e)}"
        for e in ranked))


# --- pmem export: training data ----------------------------------------------------------------


class _ModelCommand(click.Command):
    """A command whose parameters are made from a model when first needed (to parse its
    arguments or show its help), so that listing it in `pmem --help` imports nothing."""

    def __init__(self, *args: Any, make_params, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.make_params = make_params

    def get_params(self, ctx: click.Context) -> list[click.Parameter]:
        if self.make_params is not None:
            self.params = [*self.make_params(), *self.params]
            self.make_params = None
        return super().get_params(ctx)


def _export_params() -> list[click.Parameter]:
    from percept_memory.queries.export.model import ExportQuery

    return model_params(ExportQuery)


@click.pass_obj
def _export(settings: Settings, out: Path, **given: Any) -> None:
    from percept_memory.memory.store import MemoryStore
    from percept_memory.queries.export.model import ExportQuery
    from percept_memory.queries.export.run import Export, NothingExported

    query = model_from_options(ExportQuery, given)
    # stopped by a scheduler (SIGTERM) as by Ctrl-C: what it was writing is removed
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    with MemoryStore.open(settings) as store:
        export = Export(store, query, settings)
        if not export.total:
            raise click.ClickException(export.summary.why_empty())
        with progress_bar(f"export {query.format}") as bar:
            task = bar.add_task("clusters", total=export.total)
            try:
                summary = export.save(out, lambda done: bar.advance(task, done))
            except (FileExistsError, NothingExported) as error:
                raise click.ClickException(str(error)) from None
            except OSError as error:  # a missing folder, no permission, a full disk
                raise click.ClickException(f"cannot write {out}: {error.strerror}") from None
    click.echo(f"exported {summary.exported} clusters to {out}"
               + (f"; skipped: {summary.skipped_text()}" if summary.skipped else ""))


main.add_command(_ModelCommand(
    "export", callback=_export, make_params=_export_params,
    params=[click.Option(["--out"], required=True, type=click.Path(path_type=Path),
                         help="a .zip file, or a new folder")],
    help="Export the clusters a query selects as training data: FORMAT is coco, yolo, "
         "imagefolder or jsonl. The query options are those of `pmem query clusters`; each "
         "export holds provenance.jsonl and manifest.json (see README: Export). Nothing "
         "exported is an error that says why.",
    epilog=example("pmem export coco --out kitchen.zip --region table",
                   "pmem export imagefolder --out crops/ --label object --text ketchup")))


# --- corrections by people (memory/curation.py) ------------------------------------------------


def _object_id(_ctx, param, value: str | None):
    """An id argument as an ObjectId: a bad one is the command's one-line error."""
    from bson import ObjectId

    if value is None or ObjectId.is_valid(value):
        return value and ObjectId(value)
    raise click.ClickException(f"{param.name}: {value!r} is not an id (24 hexadecimal digits)")


def _object_ids(ctx, param, values: tuple[str, ...]) -> list:
    return [_object_id(ctx, param, value) for value in values]


def _author_option(command):
    import getpass

    return click.option("--author", default=getpass.getuser, show_default="your user name",
                        help="who makes the correction")(command)


@main.group(epilog=example('pmem correct relabel CLUSTER_ID "blue mug"'))
def correct() -> None:
    """Correct what the annotators said of a cluster: relabel it, reject it, merge two objects,
    split one, undo a correction. Each is stored beside the annotations, with who and when (README:
    Correcting labels)."""


def _made(make, *args) -> None:
    from percept_memory.memory import curation
    from percept_memory.memory.pipeline import rebuilding
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(click.get_current_context().obj) as store:
        try:
            made = make(store, *args)
        except curation.NotCorrectable as error:
            raise click.ClickException(str(error)) from None
        rebuilt = rebuilding(store.db)
    click.echo(f"{curation.KINDS[made.type_name]} {made.id} by {made.author}")
    if rebuilt:  # (who is who changed: the belief follows once a consolidator runs)
        click.echo(f"the belief of {', '.join(rebuilt)} is rebuilt with it by the memory "
                   "pipeline (pmem serve, or pmem consolidate); `pmem pipeline` shows how far",
                   err=True)


@correct.command(epilog=example('pmem correct relabel CLUSTER_ID "blue mug"'))
@click.argument("cluster", callback=_object_id)
@click.argument("label")
@_author_option
def relabel(cluster, label: str, author: str) -> None:
    """Say what the object seen in CLUSTER is: LABEL, its class or name."""
    from percept_memory.memory import curation

    _made(curation.relabel, cluster, label, author)


@correct.command(epilog=example("pmem correct reject CLUSTER_ID"))
@click.argument("cluster", callback=_object_id)
@click.option("--reason", default="", help="why the detection is wrong")
@_author_option
def reject(cluster, reason: str, author: str) -> None:
    """Say the detection CLUSTER is wrong: no object is there (its map's belief is rebuilt)."""
    from percept_memory.memory import curation

    _made(curation.reject, cluster, author, reason)


@correct.command(epilog=example(
    "pmem correct merge CLUSTER_ID OTHER_CLUSTER_ID"))
@click.argument("cluster", callback=_object_id)
@click.argument("other", callback=_object_id)
@_author_option
def merge(cluster, other, author: str) -> None:
    """Say CLUSTER and OTHER show the same object (their objects are merged)."""
    from percept_memory.memory import curation

    _made(curation.merge, cluster, other, author)


@correct.command(epilog=example(
    "pmem correct split OBJECT_ID CLUSTER_ID"))
@click.argument("object_id", metavar="OBJECT", callback=_object_id)
@click.argument("clusters", nargs=-1, required=True, callback=_object_ids)
@_author_option
def split(object_id, clusters, author: str) -> None:
    """Say the observations CLUSTERS of OBJECT show another object than its other
    observations (its map's belief is rebuilt: identity keeps the two sides apart)."""
    from percept_memory.memory import curation

    _made(curation.split, object_id, list(clusters), author)


@correct.command(epilog=example(
    "pmem correct undo CLUSTER_ID CORRECTION_ID"))
@click.argument("cluster", callback=_object_id)
@click.argument("correction", callback=_object_id)
@_author_option
def undo(cluster, correction, author: str) -> None:
    """Take back the CORRECTION of CLUSTER (the undo is recorded too)."""
    from percept_memory.memory import curation

    _made(curation.undo, cluster, correction, author)


@main.command(epilog=example("pmem corrections --author ana --limit 20"))
@click.option("--author", help="only the corrections of this person")
@click.option("--limit", default=50, show_default=True, type=click.IntRange(1, 1000))
@click.option("--json", "as_json", is_flag=True, help="print them as JSON")
@click.pass_obj
def corrections(settings: Settings, author: str | None, limit: int, as_json: bool) -> None:
    """The corrections people made, newest first: kind, who, when, what, on which cluster."""
    from percept_memory import answers
    from percept_memory.memory import curation
    from percept_memory.memory.store import MemoryStore

    with MemoryStore.open(settings) as store:
        rows = curation.audit(store, limit, author)
    if as_json:
        click.echo(answers.as_json(rows))
        return
    if not rows:
        raise click.ClickException("no corrections" + (f" by {author}" if author else ""))
    for row in rows:
        what = (row["label"] or row["reason"] or row["other"] or row["undoes"]
                or (row["split_off"] and f"{len(row['split_off'])} split off from "
                                          f"{len(row['apart_from'])}") or "")
        undone = f"  (undone by {row['undone_by']['author']})" if row["undone_by"] else ""
        click.echo(printable(f"{row['id']}  {row['kind']:<7} {row['author']:<12} "
                             f"{answers.iso(row['time'], precise=False)}  cluster "
                             f"{row['cluster_id']}  {what}{undone}"))
