"""Annotation types defined outside percept-memory, imported by every process pmem starts.

A type is one class, registered when its module is imported (README: Adding an annotation
type). A script imports its own modules; the processes pmem starts (the CLI, `pmem serve` and
its ingest processes, consolidators, workers) import those named by PMEM_TYPES and those an
installed package declares under the entry-point group `percept_memory.types` (as pytest finds
its plugins), so the server validates, indexes and labels them as the script would.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

ENTRY_POINTS = "percept_memory.types"


class TypeModuleError(ImportError):
    """A module of annotation types could not be imported (the message names it and why)."""


def type_modules(named: str) -> list[str]:
    """The modules named (comma-separated), then those installed packages declare."""
    listed = [name.strip() for name in named.split(",") if name.strip()]
    declared = [point.module for point in entry_points(group=ENTRY_POINTS)]
    return list(dict.fromkeys(listed + declared))


def import_type_modules(named: str) -> list[str]:
    """Import them (their types register themselves); the modules imported."""
    modules = type_modules(named)
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception as exc:  # (a module's own error too: it is named, not a traceback)
            raise TypeModuleError(f"PMEM_TYPES: cannot import {name!r}: "
                                  f"{type(exc).__name__}: {exc}") from exc
    return modules
