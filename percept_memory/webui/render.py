"""What the templates show of stored values, decided by their types, so any annotation type,
present or future (or unknown: kept as `Unknown`), renders without an edit here: numbers in
[0, 1] named like a confidence as bars, name -> share maps as bar lists, arrays as small
charts, web links as links, nested models and other maps as field tables, the rest as text."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any
from urllib.parse import urlsplit

import numpy as np
from pydantic import BaseModel

from percept_memory.converters import Unknown, name_of
from percept_memory.memory.types import LogLine

CHART_WIDTH, CHART_HEIGHT, CHART_POINTS = 240, 48, 120
SHARE_WORDS = ("confidence", "probability", "ratio", "score")
HIDDEN_FIELDS = {"id", "_id", "_type", "source"}


@dataclass
class Shown:
    """One field as the page shows it: `kind` picks the template's rendering of `value`."""

    name: str
    kind: str  # text | bar | bars | chart | links (text, is a web link) | fields
    value: Any


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
    """The fields of a model (or of an Unknown's stored document), each with its rendering."""
    items = value.fields.items() if isinstance(value, Unknown) else (
        (name, getattr(value, name)) for name in type(value).model_fields)
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
    if isinstance(value, BaseModel | Unknown):
        return Shown(name, "fields", shown_fields(value))
    if isinstance(value, Mapping) and value:  # key-values, e.g. a product's properties
        return Shown(name, "fields", [shown(str(k), v) for k, v in value.items()])
    return Shown(name, "text", _text(value))


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


def time_of(value: datetime | int | None) -> str:
    """A UTC time to the millisecond; ints are nanoseconds since the epoch."""
    if value is None:
        return ""
    if isinstance(value, int):
        value = datetime.fromtimestamp(value / 1e9, UTC)
    return value.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _empty(value: Any) -> bool:
    if isinstance(value, np.ndarray):
        return value.size == 0
    return value is None or (isinstance(value, str | list | tuple | dict) and not value)


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
    return str(value)
