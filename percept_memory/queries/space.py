"""True 3D conditions, index-backed: a few ranges of Morton keys around a volume select
candidates by index (search.morton), the exact box or distance test keeps the right ones.
MongoDB's geo indexes are 2D only; the thesis (6.6) could not use stored positions at all.

The same conditions serve clusters (`search.position`) and events (`position`), so
what-is-at a volume and changes in a volume mean exactly what a cluster search means.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass

from percept_memory.memory.search_keys import EVERYWHERE, morton_ranges

from .model import Box, Sphere

FLOAT_MAX = sys.float_info.max
MAX_RANGES = 16  # key ranges one volume is looked up by: a 1 m box is ~5 of them, holding 8
# times its volume (index keys, tested on their x, y, z without reading documents); 32 would
# hold 3.4 times its volume in ~14 ranges, but take ~4 times as long to work out in Python
KEY = "search.morton"


def keys_of_volume(volume: Box | Sphere) -> dict:
    """The condition on the Morton key that holds every position in a box or in a sphere's
    bounding box."""
    return within(morton_ranges(*corners(volume), MAX_RANGES))


def within(ranges: list[tuple[int, int]]) -> dict:
    branches = [{KEY: {"$gte": first, "$lte": last}} for first, last in ranges]
    return branches[0] if len(branches) == 1 else {"$or": branches}


def corners(volume: Box | Sphere) -> tuple[tuple, tuple]:
    if isinstance(volume, Box):
        return volume.low, volume.high
    # a sphere's bounding box, a hair wider than exact arithmetic would make it, so that no
    # point the distance test keeps is lost to rounding (it only narrows candidates)
    # (clamped to the largest float: a radius of 1e308 reaches past it, no position does)
    c, r = volume.center, volume.radius
    margin = [r + 1e-9 * (abs(v) + r) for v in c]
    return (tuple(max(v - m, -FLOAT_MAX) for v, m in zip(c, margin, strict=True)),
            tuple(min(v + m, FLOAT_MAX) for v, m in zip(c, margin, strict=True)))


@dataclass(frozen=True)
class Coordinates:
    """Where documents keep a position: the paths of x, y and z that a filter compares, and
    the expressions of them that $expr computes with."""

    paths: tuple[str, str, str]
    expressions: tuple

    @classmethod
    def array(cls, position: str) -> Coordinates:
        """A position field [x, y, z] (events)."""
        return cls(tuple(f"{position}.{axis}" for axis in range(3)),
                   tuple({"$arrayElemAt": [f"${position}", axis]} for axis in range(3)))

    @classmethod
    def scalars(cls, *paths: str) -> Coordinates:
        """x, y and z in fields of their own (clusters: the cells' index holds them, so a
        filter on them is decided in the index, without reading a document)."""
        return cls(paths, tuple(f"${path}" for path in paths))


def inside_box(box: Box, at: Coordinates) -> dict:
    """The exact test, corners included."""
    return {path: {"$gte": box.low[axis], "$lte": box.high[axis]}
            for axis, path in enumerate(at.paths)}


def squared_distance(point, coordinates: Sequence) -> dict:
    """((dx*dx + dy*dy) + dz*dz) from coordinates (expressions of x, y, z) to a point: the
    same arithmetic, in the same order, as `squared_distance_py`."""
    deltas = [{"$subtract": [coordinates[axis], float(point[axis])]} for axis in range(3)]
    squares = [{"$multiply": [d, d]} for d in deltas]
    return _plus(_plus(squares[0], squares[1]), squares[2])


def _plus(a: dict, b: dict) -> dict:
    """a + b as a - (-b): $add sums doubles with extra precision, $subtract rounds each
    step as IEEE 754 (and Python) does, so server and client agree to the last bit."""
    return {"$subtract": [a, {"$multiply": [b, -1.0]}]}


def squared_distance_py(point, position) -> float:
    dx, dy, dz = (position[axis] - point[axis] for axis in range(3))
    return (dx * dx + dy * dy) + dz * dz


def inside_sphere(sphere: Sphere, at: Coordinates) -> dict:
    """The exact test: squared distance to the centre at most the squared radius, within the
    sphere's bounding box (which lets plain range conditions narrow the candidates first)."""
    low, high = corners(sphere)
    return {**inside_box(Box(low=low, high=high), at),
            "$expr": {"$lte": [squared_distance(sphere.center, at.expressions),
                               sphere.radius * sphere.radius]}}


def inside(volume: Box | Sphere, at: Coordinates) -> dict:
    return inside_box(volume, at) if isinstance(volume, Box) else inside_sphere(volume, at)


NEAREST_REACH = tuple(0.25 * 4**step for step in range(8))  # 25 cm ... 4 km


def shells(point) -> list[tuple[dict, float]]:
    """For the k-nearest search: the key conditions of growing cubes around the point, each
    with the radius it is sure to cover (its half side: every position that near is in it);
    last every key, which covers any radius."""
    out = []
    for reach in NEAREST_REACH:
        low = [max(v - reach, -FLOAT_MAX) for v in point]
        high = [min(v + reach, FLOAT_MAX) for v in point]
        out.append((within(morton_ranges(low, high, MAX_RANGES)), reach))
    out.append((within([EVERYWHERE]), float("inf")))
    return out
