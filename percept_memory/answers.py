"""How `pmem query` shows an answer: as JSON for scripts (`--json`), or as text for people
(fields as `name: value` lines, lists as tables). Moments show in ISO 8601 UTC, in JSON with
their nanoseconds beside them (`time` and `time_ns`); "now" shows as `now`, never as the
largest int64 the engine uses for it. Moments are the fields results.py marks as such.
"""

from __future__ import annotations

import json
import typing
from typing import Any

from bson import ObjectId
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from percept_memory.memory.types import iso_from_timestamp
from percept_memory.memory.types.base import CONTROLS
from percept_memory.queries.results import NOW, Moment

COLUMNS = {  # what a table of each kind of row shows, in order
    "ClusterHit": ("id", "time", "robot", "region", "position", "labels", "score", "distance"),
    "SimilarHit": ("id", "similarity", "time", "robot", "region", "labels", "object_id"),
    "Belief": ("name", "state", "map", "region", "position", "last_seen", "confidence",
               "match", "object_id"),
    "Sighting": ("name", "state", "time", "region", "position", "robot", "cluster_id"),
    "Stay": ("region", "position", "since", "last_seen", "hidden_since", "until", "ended_by",
             "observations"),
    "ObjectAt": ("name", "state", "map", "region", "position", "since", "explanation",
                 "object_id"),
    "Moved": ("name", "before", "after", "object_id"),
    "Count": ("type", "annotator", "count"),
    "Occurrence": ("name", "region", "hour", "count", "object_id"),
    "Timing": ("annotator", "runs", "mean_ms", "max_ms", "total_ms", "warnings", "errors"),
}
MOMENT_KEYS = {"time", "first_seen", "last_seen"}  # in answers that are plain documents
NESTED = ("state", "region", "position")  # what a row's nested object shows (Moved's places)
WIDEST = 40  # characters of a cell, beyond which it is cut


def printable(text: str) -> str:
    """Stored text as a terminal shows it: each character a terminal would act on (types.
    base.CONTROLS: an escape sequence, a newline faking a row) as its escape (\\x1b)."""
    return CONTROLS.sub(lambda m: m[0].encode("unicode_escape").decode(), text)


def as_json(answer: Any) -> str:
    return json.dumps(plain(answer), indent=2)


def plain(value: Any) -> Any:
    """The answer as JSON data: models as objects, ids as strings, each moment as ISO 8601
    with its nanoseconds beside it (`<name>_ns`, null for now)."""
    if isinstance(value, BaseModel):
        data = {}
        for name, info in type(value).model_fields.items():
            item = getattr(value, name)
            if is_moment(info):
                data[name] = iso(item)
                data[f"{name}_ns"] = None if item == NOW else item
            else:
                data[name] = plain(item)
        return data
    if isinstance(value, list | tuple):
        return [plain(item) for item in value]
    if isinstance(value, dict):  # (answers made as documents: moments by their names)
        data = {}
        for key, item in value.items():
            if key in MOMENT_KEYS and isinstance(item, int) and not isinstance(item, bool):
                data[key], data[f"{key}_ns"] = iso(item), item
            else:
                data[str(key)] = plain(item)
        return data
    if isinstance(value, ObjectId):
        return str(value)
    return value


def as_text(answer: Any) -> str:
    """The answer for people: a list as a table; a model's fields as `name: value` lines,
    its lists as tables under their name, a model in it as indented lines."""
    if isinstance(answer, list):
        if answer and _has_tables(answer[0]):  # rows of rows (a history): a block each
            return "\n\n".join(as_text(row) for row in answer)
        return table(answer)
    lines = []
    for name, info in type(answer).model_fields.items():
        value = getattr(answer, name)
        if isinstance(value, list) and value and _has_tables(value[0]):  # (a comparison's
            lines += [f"{name}:", _indented("\n\n".join(map(as_text, value)))]  # cells)
        elif isinstance(value, list) and (not value or isinstance(value[0], BaseModel)):
            lines += [f"{name}:", _indented(table(value))]
        elif isinstance(value, BaseModel):  # a kind of row: as a row, else its fields
            lines += [f"{name}:", _indented(table([value]) if type(value).__name__ in COLUMNS
                                            else as_text(value))]
        else:
            lines.append(f"{name}: {cell(value, is_moment(info))}")
    return "\n".join(lines)


def _has_tables(row: Any) -> bool:
    return isinstance(row, BaseModel) and any(
        isinstance(value, list) and value and isinstance(value[0], BaseModel)
        for value in (getattr(row, name) for name in type(row).model_fields))


def table(rows: list[BaseModel]) -> str:
    """Rows under a header, columns aligned; columns empty in every row left out."""
    if not rows:
        return "(none)"
    fields = type(rows[0]).model_fields
    names = [n for n in COLUMNS.get(type(rows[0]).__name__, fields)
             if any(getattr(row, n) not in (None, []) for row in rows)]
    cells = [[cell(getattr(row, n), is_moment(fields[n])) for n in names] for row in rows]
    widths = [max(len(text) for text in column) for column in zip(names, *cells, strict=True)]
    return "\n".join("  ".join(text.ljust(width) for text, width in zip(line, widths,
                                                                         strict=True)).rstrip()
                     for line in [names, *cells])


def cell(value: Any, moment: bool = False) -> str:
    if value is None:
        return "-"
    if moment:
        return iso(value, precise=False)
    if isinstance(value, float):  # (millimetres; beyond a million metres, in e-notation)
        return f"{value:.3f}".rstrip("0").rstrip(".") if abs(value) < 1e6 else f"{value:.4g}"
    if isinstance(value, tuple):
        return "(" + ", ".join(cell(item) for item in value) + ")"
    if isinstance(value, list):
        value = ", ".join(cell(item) for item in value)
    if isinstance(value, BaseModel):  # a place (short: shown whole)
        return " ".join(cell(getattr(value, name)) for name in NESTED
                        if getattr(value, name, None) is not None)
    text = printable(str(value))
    return text if len(text) <= WIDEST else text[:WIDEST - 3] + "..."


def iso(ns: int | None, precise: bool = True) -> str | None:
    """A moment in ISO 8601 UTC: to the nanosecond, or for tables to the second."""
    if ns is None:
        return None
    if ns == NOW:
        return "now"
    text = iso_from_timestamp(ns)
    return text if precise else text[:19] + "Z"


def is_moment(info: FieldInfo) -> bool:
    return Moment in info.metadata or _marked(info.annotation)


def _marked(annotation: Any) -> bool:
    if typing.get_origin(annotation) is typing.Annotated:
        return Moment in typing.get_args(annotation)[1:]
    return any(_marked(arm) for arm in typing.get_args(annotation))


def _indented(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())
