"""Facet counts (Datasette's facets): next to each value a filter can pick, how many scenes
(the scene log) or clusters (the search page: regions, robots, and the labels and objects most
frequent among the matches) have it among those the other filters given select.

Each count is a query of that value and the other filters, which the index of the value's
field paired with time answers (schema.py: the scenes' `robot_newest`, `regions_newest`, ...,
the clusters' `region_newest`, `robot_newest`, and a text's `terms_region_robot`, whose keys
alone count a word's matches in a region; with another filter given, the planner takes the
narrower index and checks the rest on the documents it reads); the counts of one filter's
values go to the server a few commands at most. Counting stops at CAP + 1 (shown as "100+"),
so a count reads about that many index keys whatever the size of the memory, and the counts
of a page share a time budget: values left uncounted when it runs out (a rare combination of
two choices can make a count read far more) show no number rather than slowing the page.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterable, Mapping

from pymongo.collection import Collection
from pymongo.errors import ExecutionTimeout

from percept_memory.memory.search_keys import normal_label
from percept_memory.queries.clusters import compiled
from percept_memory.queries.compile import conjunction
from percept_memory.queries.model import ClusterFilter
from percept_memory.queries.ops import Runner

CAP = 100
FIELDS = {"region": "search.region", "robot": "search.robot", "labelled": "search.labels",
          "object": "object_id"}  # the search page's filters (ClusterFilter's) and their fields
FREQUENT = ("labelled", "object")  # offered by their most frequent values among the matches
TOP = 10
FEW = 5  # values of a choice counted one by one before any first look (a count each is cheap)
LOOKED = 500  # the matches read to find those
PER_COMMAND = 20
BUDGET_MS = 80  # for all the counts of a page: those it leaves uncounted show no number
SEARCH_BUDGET_MS = 60  # the search page's: its query and its 48 hits drawn fit in 100 ms too
GROUPED = 5000  # a search's matches grouped by region and robot in one first look
# (ClusterFilter's) conditions whose index holds no region or robot: their matches are read
# to be grouped. A text's are not: the `terms_region_robot` index counts them (schema.py).
GROUPED_FIRST = ("labelled", "object", "box", "sphere", "where")


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
                         choices: Mapping[str, list[str]]) -> dict[str, dict]:
    """The search page's: filter name -> value -> clusters matching the query with that value
    instead of the filter's own: for region and robot each of `choices`, for labelled and
    object the values chosen and the TOP most frequent (`frequent`: labels and objects are
    too many to offer all). A choice of FEW values (the robots, mostly) is counted value by
    value first. For the others (a building's regions), a query narrowed by a condition
    whose index holds no region (GROUPED_FIRST: a sphere, a predicate, ...) has its matches
    grouped by their fields, at most GROUPED of them (`grouped`): what that settles needs no
    count of its own. The values left open, and all those of a query of text, regions,
    robots and times (which indexes count from their keys), are counted one by one
    (`counted`), in what is left of the time (for a sphere, one count per value counted
    none in time over 1,000,000 clusters: bench/webui.py): the form's own choices first,
    then the labels and objects (a label's count with a text reads documents)."""
    deadline = time.monotonic() + SEARCH_BUDGET_MS / 1000
    without = {name: unfiltered(runner, query, [name]) for name in [*choices, *FREQUENT]}
    few = {name: values for name, values in choices.items() if len(values) <= FEW}
    counts = with_counts(clusters, without, few, {name: {} for name in few}, deadline)
    many = {name: values for name, values in choices.items() if name not in few}
    known = {name: {} for name in many}
    if many and any(getattr(query, condition) for condition in GROUPED_FIRST):
        known = grouped(clusters, unfiltered(runner, query, many), query, many, deadline)
    counts |= with_counts(clusters, without, many, known, deadline)
    offered, known = {}, {}  # then, in what time is left, the labels and objects to offer
    for name in FREQUENT:
        found = frequent(clusters, without[name], name, deadline)
        chosen = [normal_label(v) for v in query.labelled] if name == "labelled" else query.object
        offered[name] = list(dict.fromkeys([*chosen, *found]))
        known[name] = {value: n for value, n in found.items() if n is not None}
    return {**counts, **with_counts(clusters, without, offered, known, deadline)}


def unfiltered(runner: Runner, query: ClusterFilter, names: Iterable[str]) -> dict:
    """The MongoDB filter of the query without the filters `names` (compiled once a page for
    each: a text's words are looked up in the vocabulary each time)."""
    match, _ = runner.run(compiled(query.model_copy(update=dict.fromkeys(names, []))))
    return match


def with_counts(clusters: Collection, without: Mapping[str, dict],
                offered: Mapping[str, list], known: Mapping[str, dict],
                deadline: float) -> dict[str, dict]:
    """Name -> value -> count of each value offered: what is `known`, else counted with the
    query `without` that name's own filter."""
    asked = {name: {value: conjunction([without[name], {FIELDS[name]: value}])
                    for value in values if value not in known[name]}
             for name, values in offered.items()}
    counts = counted(clusters, asked, deadline)
    return {name: {value: known[name].get(value, counts[name].get(value))
                   for value in values} for name, values in offered.items()}


def frequent(clusters: Collection, match: dict, name: str, deadline: float) -> dict:
    """The TOP values of filter `name`'s field most frequent among the first LOOKED matches of
    `match` (the query without that filter), most frequent first: value -> its count if those
    were all the matches or it is over CAP among them ("CAP+" all the same), else None (to be
    counted). The look reads documents (a label's or an object's index holds no other
    condition), so it is short."""
    left_ms = int((deadline - time.monotonic()) * 1000)
    if left_ms <= 0:
        return {}
    field = f"${FIELDS[name]}"
    try:
        [found] = clusters.aggregate([
            {"$match": match}, {"$limit": LOOKED}, {"$facet": {
                "looked": [{"$count": "n"}],
                "top": [{"$unwind": field}, {"$group": {"_id": field, "n": {"$sum": 1}}},
                        {"$sort": {"n": -1, "_id": 1}}, {"$limit": TOP}]}}],
            maxTimeMS=left_ms)
    except ExecutionTimeout:
        return {}
    complete = not found["looked"] or found["looked"][0]["n"] < LOOKED
    return {row["_id"]: min(row["n"], CAP + 1) if complete or row["n"] > CAP else None
            for row in found["top"] if row["_id"] is not None}


def grouped(collection: Collection, unchosen: dict, query: ClusterFilter,
            choices: Mapping[str, list[str]], deadline: float) -> dict[str, dict[str, int]]:
    """Name -> value -> count, of the values a first look settles. `unchosen` is the query
    without any of the choices' filters; its first GROUPED matches (read by the query's own
    index: a sphere's Morton keys, a predicate's field) are grouped by every choice's field
    in one command, and each choice's value counts the groups its other choices' filters
    keep. If they are all of its matches, every count is exact; if not, a value seen more
    than CAP times among them is "CAP+" all the same. For a selective query (a few thousand
    matches across 200 regions) one command counts every region and robot, where a count per
    value would read each region's clusters for the few that match."""
    left_ms = int((deadline - time.monotonic()) * 1000)
    if left_ms <= 0:
        return {name: {} for name in choices}
    try:
        rows = list(collection.aggregate([
            {"$match": unchosen}, {"$limit": GROUPED},
            {"$group": {"_id": {name: f"${FIELDS[name]}" for name in choices},
                        "n": {"$sum": 1}}}], maxTimeMS=left_ms))
    except ExecutionTimeout:
        return {name: {} for name in choices}
    complete = sum(row["n"] for row in rows) < GROUPED
    settled = {}
    for name, values in choices.items():
        others = [other for other in choices if other != name and getattr(query, other)]
        seen = Counter()
        for row in rows:
            if all(row["_id"].get(other) in getattr(query, other) for other in others):
                seen[row["_id"].get(name)] += row["n"]
        settled[name] = {value: min(seen[value], CAP + 1) for value in values  # (as `counted`)
                         if complete or seen[value] > CAP}
    return settled


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
              cap: int) -> list[int | None]:
    """The count of each query to cap + 1, in one command: each query is a pipeline of its
    own ($unionWith) on its own index, and none waits for a round trip; all None when the
    deadline (time.monotonic) passes first."""
    left_ms = int((deadline - time.monotonic()) * 1000)
    if not queries or left_ms <= 0:
        return [None] * len(queries)
    first, *rest = [[{"$match": query}, {"$limit": cap + 1},
                     {"$group": {"_id": position, "n": {"$sum": 1}}}]
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
