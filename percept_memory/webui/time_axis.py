"""A time axis for a span of any length (the map page, issue 17): ticks at round times, every
few seconds to every few years, the smallest step that gives at most MAX_TICKS; each labelled
with what tells it apart at that step (a time of day, with the date where a day begins; a
date, a month, a year) and a link to the map at that moment, so that a map recorded over
months reads like a calendar."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime

SECOND, DAY = 1_000_000_000, 86_400
MAX_TICKS = 8
MARGIN = 40  # px left and right of the axis: room for the outer ticks' labels
STEPS = (1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 3 * 3600, 6 * 3600,
         12 * 3600, DAY, 2 * DAY, 7 * DAY, 14 * DAY)  # seconds
MONTHS = (1, 2, 3, 6, 12, 24, 60, 120, 600)
MONDAY = 4 * DAY  # the first Monday after the epoch (a Thursday): weeks start on Mondays


@dataclass
class Tick:
    t: int  # nanoseconds since the epoch
    x: float
    label: str


@dataclass
class Axis:
    width: int
    ticks: list[Tick]
    moment: float  # where the moment shown is

    @property
    def ends(self) -> tuple[int, int]:
        return MARGIN, self.width - MARGIN


def axis(start: int, end: int, moment: int, width: int) -> Axis:
    """The axis from start to end (nanoseconds) drawn width pixels wide, marking moment."""
    length = max(end - start, 1)

    def x(t: int) -> float:
        return round(MARGIN + (t - start) / length * (width - 2 * MARGIN), 1)

    times, form = _round_times(start // SECOND, -(-end // SECOND))
    times = [t for t in times if start <= t * SECOND <= end]
    ticks = [Tick(t * SECOND, x(t * SECOND), _label(t, form, i == 0 or
                                                     t // DAY != times[i - 1] // DAY))
             for i, t in enumerate(times)]
    return Axis(width, ticks, x(min(max(moment, start), end)))


def _round_times(first: int, last: int) -> tuple[list[int], str]:
    """The round times (seconds) from first to last at the smallest step that gives at most
    MAX_TICKS, and the strftime form of their labels."""
    span = max(last - first, 1)
    for step in STEPS:
        if span / step <= MAX_TICKS:
            offset = MONDAY if step % (7 * DAY) == 0 else 0
            begin = -(-(first - offset) // step) * step + offset
            form = "%H:%M:%S" if step < 60 else "%H:%M" if step < DAY else "%b %d"
            return list(range(begin, last + 1, step)), form
    for months in MONTHS:
        if span / (months * 30.4 * DAY) <= MAX_TICKS:
            break
    day = datetime.fromtimestamp(first, UTC)
    index = -(-(day.year * 12 + day.month - 1) // months) * months  # months since year 0
    times = []
    while (t := datetime(index // 12, index % 12 + 1, 1, tzinfo=UTC).timestamp()) <= last:
        times.append(int(t))
        index += months
    return times, "%Y" if months % 12 == 0 else "%Y-%m"


def _label(t: int, form: str, new_day: bool) -> str:
    """A time of day says its date too on the axis' first tick and where a day begins."""
    if new_day and form.startswith("%H"):
        form = "%b %d " + form
    return datetime.fromtimestamp(t, UTC).strftime(form)
