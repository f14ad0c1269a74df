"""Labels that never overlap, on a drawing of known size (the map page, issue 17). Each label
goes to the first free one of a few places around its point, nearest first: right, left,
above, below, the corners, then the same a step further out (joined to the point by a line).
A place is free when it lies on the drawing and overlaps no point and no label placed
before. A label without a free place is left out; the caller counts it in a marker instead.

Sizes are estimated, not measured: CHAR_WIDTH of the font size per character, and the
template pins the text to that width (SVG textLength), so what the browser draws fits."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

CHAR_WIDTH = 0.66  # of the font size: an average character of a sans-serif font, a bit more
GAP = 2.0  # px between a label and anything else
CELL = 48  # px, the side of the grid's cells that speeds up the overlap tests
RINGS = 3  # how far out a label may go, in steps of its height


@dataclass(frozen=True)
class Box:
    x: float  # left
    y: float  # top
    width: float
    height: float

    def overlaps(self, other: Box) -> bool:
        return (self.x < other.x + other.width + GAP and other.x < self.x + self.width + GAP
                and self.y < other.y + other.height + GAP and other.y < self.y + self.height + GAP)


@dataclass(frozen=True)
class Label:
    """A placed label: its box, and where its text starts (x, baseline y)."""

    text: str
    box: Box
    far: bool  # beyond the first ring: the template joins it to its point by a line

    @property
    def x(self) -> float:
        return round(self.box.x, 1)

    @property
    def y(self) -> float:
        return round(self.box.y + self.box.height * 0.78, 1)

    @property
    def width(self) -> float:
        return round(self.box.width, 1)

    def nearest(self, x: float, y: float) -> tuple[float, float]:
        """The point of the label's box nearest to (x, y): where a line to it ends."""
        return (round(min(max(x, self.box.x), self.box.x + self.box.width), 1),
                round(min(max(y, self.box.y), self.box.y + self.box.height), 1))


class Layout:
    """What is drawn so far, in a grid of cells for quick overlap tests."""

    def __init__(self, width: float, height: float, font: float):
        self.width, self.height, self.font = width, height, font
        self.cells: dict[tuple[int, int], list[Box]] = {}

    def block(self, box: Box) -> None:
        for cell in self._cells(box):
            self.cells.setdefault(cell, []).append(box)

    def is_free(self, box: Box) -> bool:
        inside = (box.x >= 0 and box.y >= 0 and box.x + box.width <= self.width
                  and box.y + box.height <= self.height)
        return inside and not any(box.overlaps(other) for cell in self._cells(box)
                                  for other in self.cells.get(cell, ()))

    def place(self, text: str, x: float, y: float, radius: float,
              rings: int = RINGS) -> Label | None:
        """The text's label beside the point (x, y) drawn with this radius, or None."""
        width, height = self.text_width(text), self.font * 1.2
        for ring, box in _around(x, y, width, height, radius, rings):
            if self.is_free(box):
                self.block(box)
                return Label(text, box, ring > 0)
        return None

    def place_at(self, text: str, corners: Iterable[tuple[float, float]]) -> Label | None:
        """The text's label at the first of these top left corners where it is free, or
        None."""
        width, height = self.text_width(text), self.font * 1.2
        for x, y in corners:
            box = Box(x, y, width, height)
            if self.is_free(box):
                self.block(box)
                return Label(text, box, False)
        return None

    def text_width(self, text: str) -> float:
        return len(text) * self.font * CHAR_WIDTH

    def _cells(self, box: Box) -> Iterator[tuple[int, int]]:
        for i in range(int(box.x // CELL) - 1, int((box.x + box.width) // CELL) + 2):
            for j in range(int(box.y // CELL) - 1, int((box.y + box.height) // CELL) + 2):
                yield i, j


def _around(x: float, y: float, width: float, height: float, radius: float,
            rings: int) -> Iterator[tuple[int, Box]]:
    """Places for a width x height label around a point, nearest first."""
    for ring in range(rings):
        r = radius + GAP + 1 + ring * (height + GAP)
        for dx, dy in ((r, -height / 2), (-r - width, -height / 2),
                       (-width / 2, -r - height), (-width / 2, r),
                       (r * 0.7, -r * 0.7 - height), (r * 0.7, r * 0.7),
                       (-r * 0.7 - width, -r * 0.7 - height), (-r * 0.7 - width, r * 0.7)):
            yield ring, Box(x + dx, y + dy, width, height)
