"""3D queries are exact: box, sphere and k-nearest against brute force on random points, at
scales from millimetres to kilometres, with query corners, centres and radii taken from the
points themselves so that boundaries are hit exactly."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from percept_memory.memory.search_keys import morton, morton_ranges
from percept_memory.memory.types import Cluster, Location, Scene
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import Box, Sphere
from percept_memory.queries.space import squared_distance_py


def random_points(rng: np.random.Generator) -> list[tuple[float, float, float]]:
    """Clumps at several scales (a cup's width to a campus), a few far away, some repeated."""
    points = []
    for scale, count in ((0.01, 60), (0.3, 80), (5.0, 80), (300.0, 40), (5000.0, 10)):
        centre = rng.uniform(-2 * scale, 2 * scale, 3)
        points += [tuple(map(float, centre + rng.normal(0, scale, 3))) for _ in range(count)]
    points += points[:10]  # the same position twice
    return [tuple(round(v, 6) for v in p) for p in points]


@pytest.fixture(scope="module")
def space(store):
    points = random_points(np.random.default_rng(7))
    scenes = [Scene(timestamp=1_000 + i, robot="probe", clusters=[
        Cluster(annotations=[Location(position=p)]) for p in points[i::20]]) for i in range(20)]
    store.put_scenes(scenes)
    by_id = {c.id: c.position for s in scenes for c in s.clusters}
    return QueryEngine(store), by_id


def all_hits(engine, **query) -> set:
    ids, cursor = set(), None
    while True:
        page = engine.clusters(**query, limit=500, **({"cursor": cursor} if cursor else {}))
        ids |= {h.id for h in page.items}
        if not page.next:
            return ids
        cursor = page.next


POSITIONS = st.integers(0, 329)
SLACK = st.sampled_from([0.0, 0.0, 1e-9, 0.001, 0.05, 1.0, 20.0, 400.0, 9000.0])
FAST = settings(max_examples=60, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@FAST
@given(a=POSITIONS, b=POSITIONS, slack=SLACK)
def test_box_is_exact(space, a, b, slack):
    engine, by_id = space
    positions = list(by_id.values())
    p, q = positions[a % len(positions)], positions[b % len(positions)]
    low = tuple(min(u, v) - slack for u, v in zip(p, q, strict=True))
    high = tuple(max(u, v) + slack for u, v in zip(p, q, strict=True))
    expected = {i for i, x in by_id.items()
                if all(lo <= v <= hi for lo, v, hi in zip(low, x, high, strict=True))}
    assert all_hits(engine, box=Box(low=low, high=high)) == expected


@FAST
@given(a=POSITIONS, b=POSITIONS, extra=SLACK)
def test_sphere_is_exact(space, a, b, extra):
    engine, by_id = space
    positions = list(by_id.values())
    centre, edge = positions[a % len(positions)], positions[b % len(positions)]
    radius = math.sqrt(squared_distance_py(centre, edge)) + extra or 0.001
    sphere = Sphere(center=centre, radius=radius)
    expected = {i for i, x in by_id.items() if squared_distance_py(centre, x) <= radius * radius}
    assert all_hits(engine, sphere=sphere) == expected


@FAST
@given(a=POSITIONS, offset=st.tuples(*[st.sampled_from([0, 0.004, -0.3, 2.5, 70.0, -4000.0])] * 3),
       k=st.integers(1, 40))
def test_nearest_are_exact(space, a, offset, k):
    engine, by_id = space
    positions = list(by_id.values())
    point = tuple(u + d for u, d in zip(positions[a % len(positions)], offset, strict=True))
    hits = engine.clusters(near=point, k=k).items
    expected = sorted(math.sqrt(squared_distance_py(point, x)) for x in by_id.values())[:k]
    assert [h.distance for h in hits] == expected
    assert all(math.sqrt(squared_distance_py(point, by_id[h.id])) == h.distance for h in hits)


COORDINATE = st.floats(-1e7, 1e7)


@settings(max_examples=300, deadline=None)
@given(low=st.tuples(COORDINATE, COORDINATE, COORDINATE),
       size=st.tuples(*[st.sampled_from([0.0, 1e-3, 0.07, 1.0, 40.0, 3e5])] * 3),
       at=st.tuples(*[st.floats(0, 1)] * 3), budget=st.integers(1, 40))
def test_the_key_ranges_of_a_box_hold_every_point_in_it(low, size, at, budget):
    high = tuple(a + s for a, s in zip(low, size, strict=True))
    point = tuple(min(a + f * s, b) for a, f, s, b in zip(low, at, size, high, strict=True))
    ranges = morton_ranges(low, high, budget)
    assert len(ranges) <= budget
    assert any(first <= morton(point) <= last for first, last in ranges)
    assert all(last < first for (_, last), (first, _) in itertools.pairwise(ranges))


def test_more_neighbours_asked_than_there_are_gives_them_all(space):
    engine, by_id = space
    assert len(engine.clusters(near=(0, 0, 0), k=1000).items) == len(by_id)


def test_the_nearest_are_ranked_from_the_index_alone(space, store):
    """Candidates are ranked by the coordinates in the Morton key's index, without reading a
    document; only the k winners are read."""
    plans: list = []
    hits = QueryEngine(store, explain=plans).clusters(near=(0, 0, 0), k=5).items
    *ranking, reading = plans
    assert len(hits) == 5 and ranking and reading["op"] == "Find"
    for plan in ranking:
        assert plan["indexes"] == ["morton_xyz"] and "FETCH" not in plan["stages"], plan


def test_a_box_is_counted_from_the_index_alone(space, store):
    """The exact test is on the coordinates the Morton key's index holds: a box's count reads no
    document (a sphere's reads those inside its bounding box, for the distance)."""
    engine, by_id = space
    low, high = (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)
    for volume, inside in (
            ({"box": Box(low=low, high=high)},
             lambda p: all(a <= v <= b for a, v, b in zip(low, p, high, strict=True))),
            ({"sphere": Sphere(center=(0, 0, 0), radius=1.0)},
             lambda p: squared_distance_py((0, 0, 0), p) <= 1.0)):
        plans: list = []
        total = QueryEngine(store, explain=plans).clusters(**volume, limit=0, count=True).total
        assert total == sum(map(inside, by_id.values())) > 0
        (plan,) = plans
        assert plan["indexes"] == ["morton_xyz"], plan
        if "box" in volume:
            assert "FETCH" not in plan["stages"], plan


def test_a_map_keeps_positions_of_other_frames_out(space, store):
    """Two maps' positions are in two frames: the same coordinates in another map are another
    place. `map` narrows any query to its maps (alone, by its own index), the box too; data
    stored before clusters knew their map get it by `reindex`."""
    engine, by_id = space
    elsewhere = Scene(timestamp=5_000, robot="probe", map="another building", clusters=[
        Cluster(annotations=[Location(position=p)]) for p in list(by_id.values())[:5]])
    store.put_scene(elsewhere)
    theirs = {c.id for c in elsewhere.clusters}
    box = Box(low=(-1e4,) * 3, high=(1e4,) * 3)
    assert all_hits(engine, box=box) >= theirs
    assert all_hits(engine, box=box, map="another building") == theirs
    assert all_hits(engine, box=box, map="probe/map").isdisjoint(theirs)
    assert all_hits(engine, near=(0, 0, 0), k=1000, map="another building") == theirs
    plans: list = []
    QueryEngine(store, explain=plans).clusters(map="another building", limit=3)
    assert [p["indexes"] for p in plans] == [["map_newest"]], plans
    store.clusters.update_many({"_id": {"$in": list(theirs)}}, {"$unset": {"search.map": ""}})
    assert not all_hits(engine, map="another building")
    store.reindex()
    assert all_hits(engine, map="another building") == theirs
