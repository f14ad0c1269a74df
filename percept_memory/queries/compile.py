"""A cluster filter compiled to a MongoDB filter, and the cursors that resume a sorted page.

The one place where query values meet MongoDB syntax. Operators and field names here are
ours; user values (validated by model.py into strings, numbers, ids and times) only ever sit
in value positions, where MongoDB never reads them as operators, and in aggregation
expressions only inside $literal. Each condition is one an index answers (see schema.py):
regions, robots, objects, time, terms, Morton keys, field entries; what an index cannot decide
exactly (a phrase, a sphere, several fields of one annotation) is checked on the candidates.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
from collections import defaultdict

from bson import ObjectId

from percept_memory.converters.registry import aliases_of, class_for
from percept_memory.memory.schema import CORRECTED
from percept_memory.memory.search_keys import AXES, normal_label

from .model import ClusterFilter, ClusterQuery
from .ops import QueryError
from .space import Coordinates, inside, keys_of_volume
from .text import Expansions, TextQuery, all_terms, phrase_pattern

PLACE = Coordinates.scalars(*(f"search.{axis}" for axis in AXES))  # the Morton index holds them


def cluster_filter(f: ClusterFilter, text: TextQuery | None = None,
                   expansions: Expansions | None = None) -> dict:
    clauses: list[dict] = []
    labels = sorted({normal_label(label) for label in f.labelled})
    for values, field in ((f.region, "search.region"), (f.robot, "search.robot"),
                          (f.map, "search.map"), (f.object, "object_id"),
                          (labels, "search.labels")):
        if values:
            clauses.append({field: {"$in": list(values)}})
    if window := time_window(f.after, f.before, f.at):
        clauses.append({"search.time": window})
    for volume in (f.box, f.sphere):
        if volume is not None:
            clauses += [keys_of_volume(volume), inside(volume, PLACE)]
    if text is not None:
        clauses.append({"search.terms": {"$in": all_terms(expansions or {})}})
        for phrase in text.phrases:
            pattern = {"$regex": phrase_pattern(phrase), "$options": "i"}
            clauses.append({"$or": [{"search.text": pattern}, {"search.labels": pattern}]})
    clauses += predicate_clauses(f)
    return conjunction(clauses)


def time_window(after: int | None, before: int | None, at: int | None = None) -> dict:
    if at is not None:
        return {"$eq": at}
    window = {}
    if after is not None:
        window["$gte"] = after
    if before is not None:
        window["$lte"] = before
    return window


def predicate_clauses(f: ClusterFilter) -> list[dict]:
    """Per annotation type, one $elemMatch over the annotations: all its predicates hold on
    the same annotation, and an index on a field of the type (store.add_field_index) gets
    bounds on both the type and the field. A label asked exactly is looked up in the labels'
    index first (every cluster with that annotation has the label, unless people corrected
    it: those few are in an index of their own), so it needs no field index to be fast."""
    by_type: dict[str, dict[str, dict]] = defaultdict(lambda: defaultdict(dict))
    again: dict[str, list[dict]] = defaultdict(list)  # an operator repeated on a field: all hold
    for p in f.where:
        if len(p.values) > 1:  # any of them (none of them, for !=), in the type's $and
            either = [{p.field: {p.operator: value}} for value in p.values]
            again[p.type] += either if p.operator == "$ne" else [{"$or": either}]
            by_type.setdefault(p.type, defaultdict(dict))  # (its $elemMatch holds them)
            continue
        operators = by_type[p.type][p.field]
        if p.operator in operators:
            again[p.type].append({p.field: {p.operator: p.value}})
        else:
            operators[p.operator] = p.value
    labels = sorted({p.label for p in f.where} - {None})
    return [*({"$or": [{"search.labels": label}, CORRECTED]} for label in labels),
            *({"annotations": {"$elemMatch": {
                "_type": stored_as(type_name), **fields, **({"$and": again[type_name]}
                                                            if again[type_name] else {})}}}
              for type_name, fields in by_type.items())]


def stored_as(type_name: str) -> str | dict:
    """The `_type`s a type's annotations are stored under: its name, and its aliases (names
    another program gave it, written by a process that did not know the class)."""
    cls = class_for(type_name)
    aliases = aliases_of(cls) if cls is not None else []
    return {"$in": [type_name, *aliases]} if aliases else type_name


def conjunction(clauses: list[dict]) -> dict:
    clauses = [c for c in clauses if c]
    return {} if not clauses else clauses[0] if len(clauses) == 1 else {"$and": clauses}


# --- cursors --------------------------------------------------------------------------------

SORT_KEYS = {"newest": ("search.time", "_id"), "oldest": ("search.time", "_id"),
             "relevance": ("score", "search.time", "_id")}


def sort_spec(sort: str) -> tuple[tuple[str, int], ...]:
    direction = 1 if sort == "oldest" else -1
    return tuple((key, direction) for key in SORT_KEYS[sort])


def fingerprint(query: ClusterQuery) -> str:
    """What a cursor is bound to: the query's filter and order (not its page size)."""
    described = json.dumps([query.filter_part().model_dump(mode="json"), query.sort],
                           sort_keys=True)
    return hashlib.sha256(described.encode()).hexdigest()[:16]


def encode_cursor(query: ClusterQuery, last: dict) -> str:
    values = [_get(last, key) for key in SORT_KEYS[query.sort]]
    values[-1] = str(values[-1])
    data = json.dumps({"q": fingerprint(query), "v": values}, separators=(",", ":"))
    return base64.urlsafe_b64encode(data.encode()).decode().rstrip("=")


def resume_after(query: ClusterQuery) -> dict:
    """The condition for the rows after the cursor's, in the query's order."""
    if query.cursor is None:
        return {}
    values = _decoded(query)
    keys = SORT_KEYS[query.sort]
    op = "$gt" if query.sort == "oldest" else "$lt"
    branches = []
    for i, key in enumerate(keys):
        branch = {k: values[j] for j, k in enumerate(keys[:i])}
        branch[key] = {op: values[i]}
        branches.append(branch)
    return {"$or": branches}


def _decoded(query: ClusterQuery) -> list:
    invalid = QueryError("the cursor is not valid: pass `next` of the previous page unchanged")
    try:
        text = query.cursor + "=" * (-len(query.cursor) % 4)
        data = json.loads(base64.urlsafe_b64decode(text.encode()))
    except (ValueError, binascii.Error, UnicodeDecodeError):
        raise invalid from None
    if not isinstance(data, dict) or data.get("q") != fingerprint(query):
        raise QueryError("the cursor belongs to another query (filter or sort changed)")
    values = data.get("v")
    keys = SORT_KEYS[query.sort]
    if not isinstance(values, list) or len(values) != len(keys):
        raise invalid
    *numbers, last_id = values
    if not all(isinstance(n, int | float) and not isinstance(n, bool) for n in numbers) or \
            not (isinstance(last_id, str) and ObjectId.is_valid(last_id)):
        raise invalid
    return [*numbers, ObjectId(last_id)]


def _get(doc: dict, dotted: str):
    for part in dotted.split("."):
        doc = doc[part]
    return doc
