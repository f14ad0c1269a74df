"""Questions to the long-term catalogue (memory/catalogue/): which objects this home has, and
whether we have seen an observation's object before.

An entry is a cluster of the catalogue's similarity graph, an object learnt: its partial
models are the views of it (each named by the cluster it was first seen in, the longest look
first), its names those of the belief objects whose tracks gave the models, and where it is now
that of the one seen last.
"""

from __future__ import annotations

from collections import Counter

from bson import ObjectId

from percept_memory.memory.catalogue.graph_of_views import GraphOfViews, modalities_consensus
from percept_memory.memory.catalogue.stage import CatalogueStage
from percept_memory.memory.catalogue.views import observation_views
from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import CATALOGUE, CATALOGUE_HISTORY, CATALOGUE_TRACKS, OBJECTS
from percept_memory.memory.store import MemoryStore

OBJECT_FIELDS = {"name": 1, "names": 1, "state": 1, "region": 1, "position": 1, "last_seen": 1}
VIEWS_SHOWN = 4


def entries(store: MemoryStore, map_name: str | None = None, limit: int = 100,
            only: list[ObjectId] | None = None, offset: int = 0) -> list[dict]:
    """The catalogue's entries (of one map, or these), the most seen first: `limit` of them
    after the first `offset`."""
    return _ranked(store, map_name, only)[offset:offset + limit]


def page(store: MemoryStore, map_name: str | None, limit: int,
         offset: int) -> tuple[list[dict], int]:
    """`limit` entries after the first `offset`, and how many there are (one read)."""
    ranked = _ranked(store, map_name)
    return ranked[offset:offset + limit], len(ranked)


def _ranked(store: MemoryStore, map_name: str | None,
            only: list[ObjectId] | None = None) -> list[dict]:
    """Every entry (of one map, or these), the most seen first."""
    match: dict = {} if map_name is None else {"map": map_name}
    if only is not None:
        match["entry"] = {"$in": only}
    groups = list(store.db[CATALOGUE].aggregate([
        {"$match": match},
        {"$group": {"_id": {"map": "$map", "entry": "$entry"}, "models": {"$push": {
            "id": "$_id", "length": "$length", "object": "$object_id", "edges": "$edges"}}}}]))
    object_ids = list({m["object"] for g in groups for m in g["models"] if m["object"]})
    objects = {doc["_id"]: doc for doc in store.db[OBJECTS].find(
        {"_id": {"$in": object_ids}}, OBJECT_FIELDS)}
    seen = {doc["_id"]: doc["seen"] for doc in store.db[CATALOGUE_TRACKS].find(
        {"_id": {"$in": object_ids}}, {"seen": 1})}
    sightings = _sightings(store, object_ids, seen)
    out = [_entry(group, objects, sightings[_key(group["_id"])]) for group in groups]
    out.sort(key=lambda e: (-e["times_seen"], e["entry"]))
    return out


def _key(entry: dict) -> tuple:
    return entry["map"], entry["entry"]


def _sightings(store: MemoryStore, object_ids: list, seen: dict) -> Counter:
    """How many sightings each entry stands for: an object's, shared by the entries holding
    its models (all of them, listed or not) in proportion to how many each holds (whole
    numbers, adding up to its own: the largest remainders round up). Counted whole in each,
    an object the catalogue holds in three entries was seen three times as often as it was."""
    holding: dict = {}  # object -> entry -> its models there
    for row in store.db[CATALOGUE].aggregate([
            {"$match": {"object_id": {"$in": object_ids}}},
            {"$group": {"_id": {"object": "$object_id", "map": "$map", "entry": "$entry"},
                        "models": {"$sum": 1}}}]):
        holding.setdefault(row["_id"]["object"], Counter())[_key(row["_id"])] = row["models"]
    out: Counter = Counter()
    for object_id, counts in holding.items():
        models = sum(counts.values())
        exact = {key: seen.get(object_id, 0) * n / models for key, n in counts.items()}
        given = {key: int(share) for key, share in exact.items()}
        left = seen.get(object_id, 0) - sum(given.values())
        for key in sorted(exact, key=lambda k: (given[k] - exact[k], str(k)))[:left]:
            given[key] += 1
        out.update(given)
    return out


def _entry(group: dict, objects: dict, sightings: int) -> dict:
    models = sorted(group["models"], key=lambda m: (-m["length"], m["id"]))
    owners = list(dict.fromkeys(m["object"] for m in models if m["object"] in objects))
    names: Counter = Counter()
    for object_id in owners:
        names.update(objects[object_id].get("names") or [objects[object_id].get("name")])
    last = max(owners, key=lambda o: objects[o].get("last_seen") or 0, default=None)
    now = None if last is None else {"object_id": str(last), **{
        k: objects[last].get(k) for k in ("name", "state", "region", "position", "last_seen")}}
    links = [{"a": str(m["id"]), "b": str(other), "weight": round(weight, 4)}
             for m in models for other, weight in m["edges"] if m["id"] < other]
    return {"entry": str(group["_id"]["entry"]), "map": group["_id"]["map"],
            "models": len(models), "views": [str(m["id"]) for m in models[:VIEWS_SHOWN]],
            "graph": {"models": [{"model": str(m["id"]), "length": m["length"]} for m in models],
                      "links": links},
            "names": [name for name, _ in names.most_common() if name],
            "times_seen": sightings,
            "objects": [str(o) for o in owners], "now": now}


def seen_before(store: MemoryStore, cluster_id: ObjectId, limit: int = 5,
                stage: CatalogueStage | None = None) -> list[dict]:
    """The entries an observation may be, best first: `inclusion`, how much of its views the
    entry holds (Duceux eq. 6.2), and `consensus`, how far its modalities agree that the entry
    is the best match (eq. 5.12)."""
    stage = stage or CatalogueStage(store)
    observation = stage.identity.observations([cluster_id]).get(cluster_id)
    if observation is None:
        raise NotFound("cluster", str(cluster_id))
    doc = store.clusters.find_one({"_id": cluster_id}, {"scene_id": 1})
    scene = store.scenes.find_one({"_id": doc["scene_id"]}, {"map": 1}) or {}
    graph = GraphOfViews.of_sequence([observation_views(observation.evidence)])
    learner = stage.learner(scene.get("map", ""))
    ranked = learner.classify(graph)[:limit]
    unions = [learner.union(entry) for entry, _ in ranked]
    found = {e["entry"]: e for e in entries(store, only=[ObjectId(e) for e, _ in ranked],
                                            limit=limit)}
    return [{**found[str(ObjectId(entry))], "inclusion": round(score, 4),
             "consensus": round(modalities_consensus(graph, union, unions), 4)}
            for (entry, score), union in zip(ranked, unions, strict=True)
            if str(ObjectId(entry)) in found]


def as_text(entry: dict) -> str:
    """One line for people: names, how often and how it was seen, where it is now."""
    now = entry["now"] or {}
    where = f"{now.get('state') or 'unknown'} at {now.get('region') or 'an unnamed place'}"
    names = ", ".join(entry["names"][:3]) or "unnamed"
    return (f"{entry['entry']}  {names}: seen {entry['times_seen']} times, "
            f"{entry['models']} views; now {where} (object {now.get('object_id')})")


def history(store: MemoryStore, map_name: str | None = None, limit: int = 50) -> list[dict]:
    """The entries that merged or split (of one map), the newest first: when, which entries
    before and after, the observation whose learning did it, and which entries after still
    are entries now (a later change may have undone one)."""
    match = {} if map_name is None else {"map": map_name}
    changes = list(store.db[CATALOGUE_HISTORY].find(match).sort([("time", -1), ("_id", -1)])
                   .limit(limit))
    named = {e for c in changes for e in c["after"]}
    current = set(store.db[CATALOGUE].distinct("entry", {"entry": {"$in": list(named)}}))
    return [{"map": c["map"], "time": c["time"], "kind": c["kind"],
             "cluster_id": str(c["cluster_id"]), "before": [str(e) for e in c["before"]],
             "after": [str(e) for e in c["after"]],
             "current": [str(e) for e in c["after"] if e in current]} for c in changes]


def similarity_graph(store: MemoryStore, map_name: str, limit: int = 10_000) -> dict:
    """The catalogue's similarity graph of one map: its partial models (named by the cluster
    each began with, with its entry, object and length) and the links kept between them, each
    once, with their weight (Duceux algorithm 5). The entries are its connected components."""
    models, links = [], []
    for doc in store.db[CATALOGUE].find({"map": map_name}, {"elements": 0}).sort(
            "_id").limit(limit):
        models.append({"model": str(doc["_id"]), "entry": str(doc["entry"]),
                       "object_id": str(doc["object_id"]) if doc["object_id"] else None,
                       "length": doc["length"]})
        links += [{"a": str(doc["_id"]), "b": str(other), "weight": round(weight, 4)}
                  for other, weight in doc["edges"] if doc["_id"] < other]
    return {"map": map_name, "models": models, "links": links}
