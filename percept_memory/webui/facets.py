"""Facet counts (Datasette's facets): next to each value a filter can pick, how many scenes
(the scene log) or clusters (the search page: regions and robots) have it among those the
other filters given select.

Each count is a query of that value and the other filters, which the index of the value's
field paired with time answers (schema.py: the scenes' `robot_newest`, `regions_newest`, ...,
the clusters' `region_newest`, `robot_newest`; with another filter given, the planner takes
the narrower index and checks the rest on the documents it reads); the counts of one filter's
values go to the server a few commands at most. Counting stops
at CAP + 1 (shown as "100+"), so a count reads about that many index keys whatever the size
of the memory, and the counts of a page share a time budget: values left uncounted when it
runs out (a rare combination of two choices can make a count read far more) show no number
rather than slowing the page.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from pymongo.collection import Collection
from pymongo.errors import ExecutionTimeout

from percept_memory.queries.clusters import compiled
from percept_memory.queries.compile import conjunction
from percept_memory.queries.model import ClusterFilter
from percept_memory.queries.ops import Runner

CAP = 100
CLUSTER_FIELDS = {"region": "search.region", "robot": "search.robot"}
PER_COMMAND = 20
BUDGET_MS = 80  # for all the counts of a page: those it leaves uncounted show no number
GROUPED = 5000  # a search's matches grouped by region (or robot) in one first look
NARROWING = ("text", "labelled", "object", "box", "sphere", "where")  # (ClusterFilter's)


def facet_counts(scenes: Collection, query: Mapping, choices: Mapping[str, list[str]],
                 fields: Mapping[str, str]) -> dict[str, dict[str, int | None]]:
    """The scene log's: filter name -> value -> scenes matching the query with that value
    instead of the filter's own (see `counted`). `query` is the scenes' filter with one key
    per filter (`fields[name]`, the field it matches)."""
    asked = {}
    for name, values in choices.items():
        others = {key: value for key, value in query.items() if key != fields[name]}
        asked[name] = {value: {**others, fields[name]: value} for value in values}
    return counted(scenes, asked)


def cluster_facet_counts(runner: Runner, clusters: Collection, query: ClusterFilter,
                         choices: Mapping[str, list[str]]) -> dict[str, dict[str, int | None]]:
    """The search page's: filter name (region, robot) -> value -> clusters matching the query
    with that value instead of the filter's own. A query narrowed by a condition of its own
    index (NARROWING: a text, a sphere, a predicate, ...) first has its matches grouped by
    the filter's field, at most GROUPED of them (`grouped`): what that counts needs no count
    of its own; the values it leaves open, and all those of a query of regions, robots and
    times alone (which their own indexes count best), are counted one by one (`counted`),
    in what is left of the time (for such a query, one count per value counted none in
    time over 1,000,000 clusters: bench/webui.py)."""
    deadline = time.monotonic() + BUDGET_MS / 1000
    narrowed = any(getattr(query, condition) for condition in NARROWING)
    asked, known = {}, {}
    for name, values in choices.items():
        match, _ = runner.run(compiled(query.model_copy(update={name: []})))
        known[name] = (grouped(clusters, match, CLUSTER_FIELDS[name], values, deadline)
                       if narrowed else {})
        asked[name] = {value: conjunction([match, {CLUSTER_FIELDS[name]: value}])
                       for value in values if value not in known[name]}
    counts = counted(clusters, asked, deadline)
    return {name: {value: known[name].get(value, counts[name].get(value))
                   for value in values} for name, values in choices.items()}


def grouped(collection: Collection, match: dict, field: str, values: list[str],
            deadline: float) -> dict[str, int]:
    """Value -> count, of the values a first look settles: the query's first GROUPED matches
    (read by the query's own index: a text's words, a sphere's cells, a predicate's field),
    grouped by the field. If they are all of its matches, every count is exact; if not, a
    value seen more than CAP times among them is "CAP+" all the same. For a selective query
    (a few thousand matches across 200 regions) one command counts every region, where a
    count per region would read each region's clusters for the few that match."""
    left_ms = int((deadline - time.monotonic()) * 1000)
    if left_ms <= 0:
        return {}
    try:
        rows = list(collection.aggregate([
            {"$match": match}, {"$limit": GROUPED},
            {"$group": {"_id": f"${field}", "n": {"$sum": 1}}}], maxTimeMS=left_ms))
    except ExecutionTimeout:
        return {}
    seen = {row["_id"]: min(row["n"], CAP + 1) for row in rows}  # (as `counted` counts)
    if sum(row["n"] for row in rows) < GROUPED:
        return {value: seen.get(value, 0) for value in values}
    return {value: seen[value] for value in values if seen.get(value, 0) > CAP}


def counted(collection: Collection, asked: Mapping[str, Mapping[str, dict]],
            deadline: float | None = None) -> dict[str, dict[str, int | None]]:
    """Name -> value -> how many documents its filter selects, at most CAP + 1; None when the
    page's time for counting (from now, or until `deadline`) ran out first. Counts go
    PER_COMMAND values to a command, the filters with the fewest values first, so a budget
    that runs out leaves the long lists (a building's 200 regions) partly uncounted rather
    than everything."""
    deadline = deadline or time.monotonic() + BUDGET_MS / 1000
    counts: dict[str, dict[str, int | None]] = {}
    for name in sorted(asked, key=lambda name: len(asked[name])):  # the fewest values first
        values = list(asked[name])
        counts[name] = {}
        for start in range(0, len(values), PER_COMMAND):
            some = values[start:start + PER_COMMAND]
            found = counts_of(collection, [asked[name][v] for v in some], deadline, CAP)
            counts[name].update(zip(some, found, strict=True))
    return {name: counts[name] for name in asked}


def counts_of(collection: Collection, queries: list[dict], deadline: float,
              cap: int | None) -> list[int | None]:
    """The count of each query (to cap + 1, if a cap is given), in one command: each query is
    a pipeline of its own ($unionWith) on its own index, and none waits for a round trip;
    all None when the deadline (time.monotonic) passes first."""
    left_ms = int((deadline - time.monotonic()) * 1000)
    if not queries or left_ms <= 0:
        return [None] * len(queries)
    limit = [] if cap is None else [{"$limit": cap + 1}]
    first, *rest = [[{"$match": query}, *limit, {"$group": {"_id": position, "n": {"$sum": 1}}}]
                    for position, query in enumerate(queries)]
    pipeline = first + [{"$unionWith": {"coll": collection.name, "pipeline": p}} for p in rest]
    try:
        found = {row["_id"]: row["n"]
                 for row in collection.aggregate(pipeline, maxTimeMS=left_ms)}
    except ExecutionTimeout:
        return [None] * len(queries)
    return [found.get(position, 0) for position in range(len(queries))]  # no row: none


def shown(count: int | None) -> str:
    """A count as the page shows it: "12", "1000+", or nothing when it was not counted."""
    if count is None:
        return ""
    return f"{CAP}+" if count > CAP else f"{count:,}"
