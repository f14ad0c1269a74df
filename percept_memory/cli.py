"""`pmem`, the command line of percept-memory: one click group, one section per subcommand.

Results go to stdout (so `export MONGODB_URI=$(pmem db start)` works); progress, warnings and
errors go to stderr. Expected failures print `Error: <what happened and what to do>` and exit
with code 1, never a traceback.
"""

from __future__ import annotations

import json
import logging
from typing import Any

import click
from pydantic import ValidationError

from percept_memory.memory.errors import StoreError, redacted
from percept_memory.memory.mongod import EmbeddedMongod, EmbeddedMongoError
from percept_memory.memory.settings import Settings, settings_help
from percept_memory.memory.store import MemoryStore

HELP = f"""percept-memory: a long-term spatio-temporal memory for robot perception.

Settings come from these environment variables:

\b
{settings_help()}"""


class _Group(click.Group):
    """The top-level group: turns our expected failures into click's `Error: ...` exit."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except (EmbeddedMongoError, StoreError, ValidationError) as exc:
            raise click.ClickException(str(exc)) from exc


class _StderrHandler(logging.Handler):
    """Shows the library's progress and warnings on whatever stderr is at the time of the call."""

    def emit(self, record: logging.LogRecord) -> None:
        prefix = f"{record.levelname.capitalize()}: " if record.levelno >= logging.WARNING else ""
        click.echo(prefix + record.getMessage(), err=True)


@click.group(cls=_Group, help=HELP)
@click.pass_context
def main(ctx: click.Context) -> None:
    logger = logging.getLogger("percept_memory")
    logger.handlers = [_StderrHandler()]
    logger.setLevel(logging.INFO)
    ctx.obj = Settings()


# --- pmem db: the embedded mongod --------------------------------------------------------------


@main.group()
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


@db.command()
@click.pass_obj
def start(settings: Settings) -> None:
    """Start the embedded mongod (or reuse the running one) and print its URI."""
    if not _external_database(settings):
        click.echo(EmbeddedMongod.from_settings(settings).start())


@db.command()
@click.pass_obj
def stop(settings: Settings) -> None:
    """Shut the embedded mongod down cleanly."""
    if not _external_database(settings):
        EmbeddedMongod.from_settings(settings).stop()


@db.command()
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
        click.echo(f"{key + ':':<12}{_readable(key, value)}")


def _readable(key: str, value: Any) -> str:
    if value is None:
        return "-"
    if key == "running":
        return "yes" if value else "no"
    if key == "size_bytes":
        return f"{value / 2**20:.1f} MiB"
    return str(value)


# --- pmem info: what the memory holds ------------------------------------------------------------


@main.command()
@click.option("--json", "as_json", is_flag=True, help="Print the counts as JSON.")
@click.pass_obj
def info(settings: Settings, as_json: bool) -> None:
    """Show the database in use and how many documents and annotations of each type it holds."""
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
