"""What the templates show of stored values, decided by their types, so any annotation type,
present or future (or unknown: kept as `Unknown`), renders without an edit here: numbers in
[0, 1] named like a confidence as bars, name -> share maps as bar lists, arrays as small
charts, web links as links, nested models and other maps as collapsible field tables, lists
of them (a RoboSherlock contour of rs.cv.Point) as one collapsible table, the rest as text.
Nothing is shown as a Python repr: a foreign document's ids and parents are hidden, lists of
scalars are joined."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any
from urllib.parse import urlsplit

import numpy as np
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from percept_memory.converters import Unknown, name_of
from percept_memory.memory.types import LogLine, is_timestamp

CHART_WIDTH, CHART_HEIGHT, CHART_POINTS = 240, 48, 120
SHARE_WORDS = ("confidence", "probability", "ratio", "score")
HIDDEN_FIELDS = {"id", "_id", "_type", "_parent", "source"}
OPEN_FIELDS = 4  # a nested table of at most this many fields shows open
MAX_ROWS, MAX_ITEMS = 20, 40  # rows of a list of records, items of a list of scalars shown


@dataclass
class Shown:
    """One field as the page shows it: `kind` picks the template's rendering of `value`."""

    name: str
    kind: str  # text | bar | bars | chart | links (text, is a web link) | fields | records
    value: Any
    summary: str = ""  # what a collapsed fields or records table holds


@dataclass
class Records:
    """A list of documents as one table: a column per field any of the first rows has."""

    columns: list[str]
    rows: list[dict[str, Shown]]
    more: int  # rows not shown


@dataclass
class Chart:
    """A small inline SVG line chart of an array, flattened (values as given, in order)."""

    points: str
    count: int
    shape: tuple
    low: float
    high: float
    width: int = CHART_WIDTH
    height: int = CHART_HEIGHT


def type_name(value: Any) -> str:
    if isinstance(value, Unknown):
        return value.type_name
    return name_of(type(value)) or type(value).__name__


def shown_fields(value: Any) -> list[Shown]:
    """The fields of a model, an Unknown's stored document or a map, each with its rendering."""
    if isinstance(value, Unknown):
        items = value.fields.items()
    elif isinstance(value, Mapping):
        items = ((str(k), v) for k, v in value.items())
    else:
        items = ((name, _timed(getattr(value, name), info))
                 for name, info in type(value).model_fields.items())
    return [shown(name, field) for name, field in items
            if name not in HIDDEN_FIELDS and not _empty(field)]


def shown(name: str, value: Any) -> Shown:
    if _is_share(name, value):
        return Shown(name, "bar", float(value))
    if _is_shares(value):
        ranked = sorted(value.items(), key=lambda item: -item[1])
        return Shown(name, "bars", [(str(k), float(v)) for k, v in ranked])
    if isinstance(value, np.ndarray) and value.size > 1 and value.dtype.kind in "iuf":
        return Shown(name, "chart", chart(value))
    if _has_links(value):
        return Shown(name, "links", [(v, _is_web_link(v)) for v in value])
    if _is_document(value):
        fields = shown_fields(value)
        count, named = f"{len(fields)} fields", _type_of(value)
        return Shown(name, "fields", fields, f"{named}, {count}" if named else count)
    if isinstance(value, list | tuple) and value and all(map(_is_document, value)):
        return Shown(name, "records", records(value),
                     f"{len(value)} × {_type_of(value[0]) or 'documents'}")
    return Shown(name, "text", _text(value))


def records(documents: list | tuple) -> Records:
    """The first MAX_ROWS documents as rows: a contour may hold thousands of points."""
    rows = [{item.name: item for item in shown_fields(d)} for d in documents[:MAX_ROWS]]
    columns = list(dict.fromkeys(name for row in rows for name in row))
    return Records(columns, rows, len(documents) - len(rows))


def chart(values: np.ndarray) -> Chart:
    """At most CHART_POINTS points (bins averaged), scaled into the chart box."""
    flat = values.astype(float).ravel()
    flat = flat[np.isfinite(flat)]
    bins = np.array_split(flat, min(CHART_POINTS, max(1, flat.size)))
    means = np.array([b.mean() for b in bins if b.size])
    low, high = (float(means.min()), float(means.max())) if means.size else (0.0, 0.0)
    span = high - low or 1.0
    xs = np.linspace(0, CHART_WIDTH, means.size) if means.size > 1 else np.zeros(means.size)
    ys = CHART_HEIGHT - 2 - (means - low) / span * (CHART_HEIGHT - 4)
    points = " ".join(f"{x:.1f},{y:.1f}" for x, y in zip(xs, ys, strict=True))
    return Chart(points, int(values.size), tuple(values.shape), low, high)


def log_by_annotator(log: list[LogLine]) -> list[tuple[str, float, list[LogLine]]]:
    """The log lines grouped by annotator (first appearance first), with their total time."""
    groups: dict[str, list[LogLine]] = {}
    for line in log:
        groups.setdefault(line.source or "(no annotator)", []).append(line)
    return [(source, sum(line.duration_ms or 0 for line in lines), lines)
            for source, lines in groups.items()]


def time_of(value: datetime | int | str | None) -> str:
    """A UTC time to the millisecond; ints are nanoseconds since the epoch, strings ISO 8601
    (as the API gives them)."""
    if value is None:
        return ""
    if isinstance(value, int):
        value = datetime.fromtimestamp(value / 1e9, UTC)
    elif isinstance(value, str):
        value = datetime.fromisoformat(value)
    return value.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _timed(value: Any, field: FieldInfo) -> Any:
    """A Timestamp field's value as a time (people read no nanoseconds since 1970)."""
    return time_of(value) if value is not None and is_timestamp(field) else value


def _empty(value: Any) -> bool:
    if isinstance(value, np.ndarray):
        return value.size == 0
    return value is None or (isinstance(value, str | list | tuple | dict) and not value)


def _is_document(value: Any) -> bool:
    """A model, an Unknown, or a map: anything shown as a table of fields."""
    return isinstance(value, BaseModel | Unknown) or (isinstance(value, Mapping) and bool(value))


def _type_of(document: Any) -> str | None:
    """A document's type name (a foreign one's `_type`); None for a plain map."""
    if isinstance(document, Mapping):
        named = document.get("_type")
        return named if isinstance(named, str) else None
    return type_name(document)


def _is_share(name: str, value: Any) -> bool:
    return (any(word in name.lower() for word in SHARE_WORDS) and _is_number(value)
            and 0 <= value <= 1)


def _is_shares(value: Any) -> bool:
    """A name -> share map, such as per-class confidences or colour ratios."""
    return (isinstance(value, Mapping) and bool(value)
            and all(_is_number(v) and 0 <= v <= 1 for v in value.values()))


def _has_links(value: Any) -> bool:
    return (isinstance(value, list) and all(isinstance(v, str) for v in value)
            and any(_is_web_link(v) for v in value))


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)


def _is_web_link(text: str) -> bool:
    """Only http(s) addresses become links: a `javascript:` one from a web result stays text."""
    return urlsplit(text).scheme in ("http", "https")


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, tuple | list) and all(isinstance(v, float) for v in value):
        return "(" + ", ".join(f"{v:.3f}" for v in value) + ")"
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array {value.shape}"
    if isinstance(value, tuple | list):
        shown = ", ".join(_text(v) for v in value[:MAX_ITEMS])
        return shown + (f", … ({len(value) - MAX_ITEMS} more)" if len(value) > MAX_ITEMS else "")
    if isinstance(value, Mapping):  # in a list of mixed items
        return "{" + ", ".join(f"{k}: {_text(v)}" for k, v in value.items()
                               if k not in HIDDEN_FIELDS) + "}"
    return cut(str(value))


MAX_SHOWN = 2000  # characters of a text a page shows (a text may hold a MiB)


def cut(text: str) -> str:
    """A text as a page shows it: its first MAX_SHOWN characters, and how many more."""
    if len(text) <= MAX_SHOWN:
        return text
    return f"{text[:MAX_SHOWN]}… ({len(text) - MAX_SHOWN:,} more characters)"
