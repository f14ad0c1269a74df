"""The annotators page's charts and confusion tables. The charts are drawn on the server as
SVG (readable without JavaScript, each mark with a hover title and reachable from the
keyboard): per annotator, its median and 95th percentile time hour by hour, two lines broken
where an hour has no run; and the share of each hour's scenes in which it warned or failed,
as bars. All charts share one axis of the window's hours, so their hours line up one above
the other. The axis has a slot per hour with a scene, not a scale of time: a window of the
latest scenes may span years with long silences (the demo's RoboSherlock scenes of 2016 and
its kitchen week of 2024), which a time scale would squeeze into two slivers; a silence is
drawn as a break, its span in its title."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from datetime import UTC, datetime

from percept_memory.queries.annotators import HOUR_NS
from percept_memory.queries.results import (
    AnnotatorHour,
    AnnotatorReport,
    Comparison,
    ConfusionCount,
)

WIDTH = 600
TIMES_HEIGHT, RATES_HEIGHT = 150, 80  # px, each chart's
TOP, BOTTOM = 10, 30  # px above the plot, and below it for the time axis
MAX_BAR = 14  # px: a bar's widest
MARGIN = 44  # px left and right of the plots: room for the value axis' labels
MAX_TICKS = 6


@dataclass
class Mark:
    x: float
    title: str
    y50: float = 0.0  # the times chart: the median's and the 95th percentile's height
    y95: float = 0.0
    warned: tuple[float, float] = (0.0, 0.0)  # the rates chart: a bar's top and height
    failed: tuple[float, float] = (0.0, 0.0)


@dataclass
class Chart:
    annotator: str
    height: int
    marks: list[Mark] = field(default_factory=list)
    lines: list[tuple[str, str]] = field(default_factory=list)  # (median, p95) point lists
    ticks: list[tuple[float, str]] = field(default_factory=list)  # the value axis: (y, label)


@dataclass
class Tick:
    x: float
    label: str


@dataclass
class Break:
    x: float
    title: str


@dataclass
class HourAxis:
    width: int
    ticks: list[Tick]
    breaks: list[Break]  # between two hours with scenes, more than an hour apart

    @property
    def ends(self) -> tuple[int, int]:
        return MARGIN, self.width - MARGIN


@dataclass
class Charts:
    axis: HourAxis
    bar: float  # a rate bar's width
    times: list[Chart]
    rates: list[Chart]


def charts(report: AnnotatorReport) -> Charts | None:
    """The window's charts; None for a window without a log line."""
    hours = sorted({h.hour for h in report.hours})
    if not hours:
        return None
    slot = (WIDTH - 2 * MARGIN) / len(hours)
    where = {hour: round(MARGIN + (i + 0.5) * slot, 1) for i, hour in enumerate(hours)}
    by_annotator: dict[str, list[AnnotatorHour]] = {}
    for hour in report.hours:
        by_annotator.setdefault(hour.annotator, []).append(hour)
    bar = round(max(1.0, min(MAX_BAR, slot / 2 - 1)), 1)
    return Charts(axis=_axis(hours, slot), bar=bar,
                  times=[c for hs in by_annotator.values() if (c := _times(hs, where))],
                  rates=[c for hs in by_annotator.values() if (c := _rates(hs, where, bar))])


def _axis(hours: list[int], slot: float) -> HourAxis:
    """At most MAX_TICKS labels, evenly among the slots, each with its date where it is not
    the previous label's; a break wherever hours with scenes are more than an hour apart."""
    every = math.ceil(len(hours) / MAX_TICKS)
    ticks, previous = [], None
    for i in range(0, len(hours), every):
        moment = datetime.fromtimestamp(hours[i] / 1e9, UTC)
        form = ("%H:00" if previous and moment.date() == previous.date() else
                "%b %d %H:00" if previous and moment.year == previous.year else "%Y %b %d %H:00")
        ticks.append(Tick(round(MARGIN + (i + 0.5) * slot, 1), moment.strftime(form)))
        previous = moment
    breaks = [Break(round(MARGIN + i * slot, 1),
                    f"no scene from {_start(before + HOUR_NS)} to {_start(after)} UTC")
              for i, (before, after) in enumerate(itertools.pairwise(hours), 1)
              if after - before > HOUR_NS]
    return HourAxis(WIDTH, ticks, breaks)


def _times(hours: list[AnnotatorHour], x: dict[int, float]) -> Chart | None:
    """Median and 95th percentile per hour with runs; None if it never logged a time."""
    timed = [h for h in hours if h.p95_ms is not None]
    if not timed:
        return None
    chart = Chart(hours[0].annotator, TIMES_HEIGHT)
    top = _round_up(max(h.p95_ms for h in timed))
    plot = TIMES_HEIGHT - TOP - BOTTOM

    def y(ms: float) -> float:
        return round(TOP + plot * (1 - ms / top), 1)

    chart.ticks = [(y(v), f"{v:g} ms") for v in (0, top / 2, top)]
    run: list[Mark] = []
    for i, h in enumerate(timed):
        mark = Mark(x[h.hour], f"{h.annotator}, {_hour(h.hour)}: median {h.p50_ms:.1f} ms, "
                    f"95th percentile {h.p95_ms:.1f} ms ({h.runs} run{'s' * (h.runs != 1)})",
                    y50=y(h.p50_ms), y95=y(h.p95_ms))
        chart.marks.append(mark)
        if run and h.hour - timed[i - 1].hour > HOUR_NS:  # an hour without a run: a gap
            chart.lines.append(_polylines(run))
            run = []
        run.append(mark)
    chart.lines.append(_polylines(run))
    return chart


def _rates(hours: list[AnnotatorHour], x: dict[int, float], bar: float) -> Chart | None:
    """Per hour, the share of its scenes the annotator warned in, and failed in; None if it
    did neither in the window."""
    if not any(h.warned or h.failed for h in hours):
        return None
    chart = Chart(hours[0].annotator, RATES_HEIGHT)
    plot = RATES_HEIGHT - TOP - BOTTOM
    chart.ticks = [(TOP + plot * (1 - share), f"{share:.0%}") for share in (0, 0.5, 1)]
    for h in hours:
        if h.warned or h.failed:
            warned, failed = h.warned / h.scenes, h.failed / h.scenes
            chart.marks.append(Mark(
                x[h.hour], f"{h.annotator}, {_hour(h.hour)}: warned in {h.warned} and failed "
                           f"in {h.failed} of {h.scenes} scene{'s' * (h.scenes != 1)} "
                           f"({warned:.0%}, {failed:.0%})",
                warned=(round(TOP + plot * (1 - warned), 1), round(plot * warned, 1)),
                failed=(round(TOP + plot * (1 - failed), 1), round(plot * failed, 1))))
    return chart


def _polylines(run: list[Mark]) -> tuple[str, str]:
    return (" ".join(f"{m.x},{m.y50}" for m in run), " ".join(f"{m.x},{m.y95}" for m in run))


def _round_up(value: float) -> float:
    """The round number (1, 2 or 5 times a power of ten) at or above value."""
    if value <= 0:
        return 1.0
    power = 10.0 ** math.floor(math.log10(value))
    return next(step * power for step in (1, 2, 5, 10) if step * power >= value)


def _start(hour: int) -> str:
    return f"{datetime.fromtimestamp(hour / 1e9, UTC):%Y-%m-%d %H}:00"


def _hour(start: int) -> str:
    return f"{_start(start)}–{(start // HOUR_NS + 1) % 24:02d}:00 UTC"


@dataclass
class Table:
    """A comparison laid out as a table: the reference's classes down, the annotator's
    across, each in order of name and "said nothing" (None) last."""

    said: list[str | None]
    expected: list[str | None]
    counts: dict[tuple[str | None, str | None], ConfusionCount]


def confusion_table(comparison: Comparison) -> Table:
    def ordered(values: set) -> list:
        return sorted(values, key=lambda v: (v is None, v or ""))

    return Table(said=ordered({c.said for c in comparison.cells}),
                 expected=ordered({c.expected for c in comparison.cells}),
                 counts={(c.said, c.expected): c for c in comparison.cells})
