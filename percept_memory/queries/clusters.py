"""Finding clusters: a page in time order or by relevance, or the k nearest to a point."""

from __future__ import annotations

import math

from percept_memory.memory.schema import CLUSTERS

from . import meaning
from .compile import (
    PLACE,
    cluster_filter,
    conjunction,
    encode_cursor,
    resume_after,
    sort_spec,
)
from .model import ClusterFilter, ClusterQuery
from .ops import Aggregate, Count, Find, Plan, QueryError
from .results import ClusterHit, ClusterPage
from .space import shells, squared_distance
from .text import MEANING, TextQuery, expand, score_expression

RANK_WINDOW = 300  # relevance ranks the most recent this many text matches
HIT_FIELDS = {"scene_id": 1, "object_id": 1, **{f"search.{key}": 1 for key in (
    "time", "robot", "region", "position", "labels", "text", "types")}}


def compiled(f: ClusterFilter) -> Plan[tuple[dict, dict | None]]:
    """The MongoDB filter of a cluster filter, and the text's word expansions (if any)."""
    if f.text is None:
        return cluster_filter(f), None
    text = TextQuery.parse(f.text)
    if not text.words:
        raise QueryError(f"the text {f.text!r} has no words to search for")
    expansions = yield from expand(text.words)
    if f.meaning and (meant := (yield from meaning.neighbours(" ".join(text.words)))):
        expansions[MEANING] = meant
    return cluster_filter(f, text, expansions), expansions


def find_clusters(query: ClusterQuery) -> Plan[ClusterPage]:
    """Clusters (observations) matching text, regions, robots, objects, a box, a sphere, a
    time range and annotation field predicates: a page, newest first (or oldest first, or by
    relevance to the text), with the cursor of the next page; or the k nearest to a point."""
    match, expansions = yield from compiled(query)
    if query.near is not None:
        return ClusterPage(items=(yield from nearest(match, query.near, query.k)))
    if query.limit == 0:  # the count alone: one round trip, no document read for a page
        return ClusterPage(items=[], total=(yield Count(CLUSTERS, match)))
    if query.sort == "relevance":
        docs = yield Aggregate(CLUSTERS, [
            {"$match": match},
            {"$sort": {"search.time": -1, "_id": -1}},
            {"$limit": RANK_WINDOW},
            {"$project": {**HIT_FIELDS,
                          "score": score_expression(expansions, "$search.terms")}},
            *([{"$match": resume_after(query)}] if query.cursor else []),
            {"$sort": dict(sort_spec("relevance"))},
            {"$limit": query.limit + 1},
        ])
    else:
        docs = yield Find(CLUSTERS, conjunction([match, resume_after(query)]), HIT_FIELDS,
                          sort_spec(query.sort), query.limit + 1)
    total = (yield Count(CLUSTERS, match)) if query.count else None
    more = len(docs) > query.limit
    return ClusterPage(items=[ClusterHit.of(d) for d in docs[:query.limit]],
                       next=encode_cursor(query, docs[query.limit - 1]) if more else None,
                       total=total)


def nearest(match: dict, point, k: int) -> Plan[list[ClusterHit]]:
    """The k matching clusters nearest to the point, nearest first: the cubes of cells around
    it grow until the k-th nearest candidate lies within the radius the cube covers, so no
    cluster outside the cube can be nearer. Candidates are ranked by the coordinates the
    Morton key's index holds (without reading their documents when nothing else is asked),
    and only the k found are read."""
    for keys, covered in shells(point):
        ranked = yield Aggregate(CLUSTERS, [
            {"$match": conjunction([match, keys])},
            {"$project": {"time": "$search.time",
                          "d2": squared_distance(point, PLACE.expressions)}},
            {"$sort": {"d2": 1, "time": -1, "_id": -1}},
            {"$limit": k},
        ])
        if math.isinf(covered) or (len(ranked) == k and
                                    math.sqrt(ranked[-1]["d2"]) < covered * (1 - 1e-9)):
            break
    if not ranked:
        return []
    found = yield Find(CLUSTERS, {"_id": {"$in": [r["_id"] for r in ranked]}}, HIT_FIELDS)
    docs = {d["_id"]: d for d in found}
    return [ClusterHit.of({**docs[r["_id"]], "distance": math.sqrt(r["d2"])}) for r in ranked]
