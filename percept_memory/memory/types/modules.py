"""Annotation types defined outside percept-memory, imported by every process pmem starts.

A type is one class, registered when its module is imported (README: Adding an annotation
type). A script imports its own modules; the processes pmem starts (the CLI, `pmem serve` and
its ingest processes, consolidators, workers) import those named by PMEM_TYPES and those an
installed package declares under the entry-point group `percept_memory.types` (as pytest finds
its plugins), so the server validates, indexes and labels them as the script would.
"""

from __future__ import annotations

import importlib
from functools import cache
from importlib.metadata import entry_points

ENTRY_POINTS = "percept_memory.types"


class TypeModuleError(ImportError):
    """A module of annotation types could not be imported (the message names it and why)."""


def type_modules(named: str) -> dict[str, str]:
    """The modules named (comma-separated), then those installed packages declare, each with
    where it is named (to say so when it cannot be imported)."""
    listed = {name.strip(): "PMEM_TYPES" for name in named.split(",") if name.strip()}
    return {**declared(), **listed}


@cache
def declared() -> dict[str, str]:
    """The modules installed packages declare: read once a process (a scan of every
    installed package, ~30 ms, which each opening of the memory would do again)."""
    return {point.module: f"the entry point {point.name!r} of "
                          f"{point.dist.name if point.dist else 'a package'}"
            for point in entry_points(group=ENTRY_POINTS)}


def import_type_modules(named: str) -> list[str]:
    """Import them (their types register themselves); the modules imported."""
    modules = type_modules(named)
    for name, where in modules.items():
        try:
            importlib.import_module(name)
        except (Exception, SystemExit) as exc:  # (a module's own error too: named)
            raise TypeModuleError(f"{where}: cannot import {name!r}: "
                                  f"{type(exc).__name__}: {exc}") from None
    return list(modules)
