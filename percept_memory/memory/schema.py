"""Collections, their indexes and the `types` catalogue: the database layout in one place."""

from __future__ import annotations

import types
import typing
from typing import Any

from pymongo import ASCENDING, DESCENDING, IndexModel

from percept_memory.converters import aliases_of, class_for, foreign_codec_names, name_of

SCENES = "scenes"
CLUSTERS = "clusters"
OBJECTS = "objects"
EVENTS = "events"
CALIBRATION = "calibration"  # what identity resolution learnt about the sensors, per map
OUTBOX = "outbox"  # per stored scene, the after-store stages it awaits (memory/pipeline.py)
MAPS = "maps"  # per map: how far its belief is, and the lease of its one writer
JOBS = "jobs"
LOOKUP_CACHE = "lookup_cache"
TYPES = "types"
TERMS = "terms"  # the words clusters use, digits aside, with their trigrams (for misspellings)
LABELS = "labels"  # labels of several words, by their words (objects by any word of a name)
CATALOGUE = "catalogue"  # the partial models of the long-term catalogue (memory/catalogue/)
CATALOGUE_TRACKS = "catalogue_tracks"  # per object, the partial model its views go to now
CATALOGUE_HISTORY = "catalogue_history"  # the catalogue's entries that merged or split, when
BINARIES = "binaries"  # content id -> bytes: the binaries too big for the documents queries read
GRIDFS_FILES = "fs.files"  # and those too big for one document of their own
GRIDFS_CHUNKS = "fs.chunks"


CORRECTED = {"annotations.author": {"$exists": True}}  # the clusters people corrected


def _newest(*keys: str, name: str, then: tuple[str, ...] = ()) -> IndexModel:
    """An index on `keys` then newest first: (time, _id) descending; `then` after those, for
    queries the index can answer without reading documents."""
    return IndexModel([*((key, ASCENDING) for key in keys), ("search.time", DESCENDING),
                       ("_id", DESCENDING), *((key, ASCENDING) for key in then)], name=name)


INDEXES: dict[str, list[IndexModel]] = {
    SCENES: [
        IndexModel([("robot", ASCENDING), ("timestamp", ASCENDING)], unique=True,
                   name="robot_time_unique"),
        # the scene log (webui/scene_log.py): newest first, (timestamp, _id) as its cursor,
        # unfiltered or filtered by any one of these fields
        IndexModel([("timestamp", DESCENDING), ("_id", DESCENDING)], name="newest"),
        # a map's scenes in time order: its belief rebuilt (memory/pipeline.py), its span
        IndexModel([("map", ASCENDING), ("timestamp", ASCENDING), ("_id", ASCENDING)],
                   name="map_time"),
        *(IndexModel([(key, ASCENDING), ("timestamp", DESCENDING), ("_id", DESCENDING)],
                     name=f"{key.rpartition('.')[2]}_newest")
          for key in ("robot", "summary.regions", "summary.annotators", "summary.types")),
        # a robot's scenes where an annotator failed, in time order (queries/playback.py):
        # only those scenes are in it
        IndexModel([("robot", ASCENDING), ("timestamp", ASCENDING)], name="robot_failed_time",
                   partialFilterExpression={"log.level": "error"}),
    ],
    # Each query path of queries/ has an index ending in (time, _id): results come newest
    # first, and a cursor resumes after the last (time, _id) seen, without sorting in memory.
    # Nothing else is indexed: each index entry costs every write (bench/ingest.py).
    CLUSTERS: [
        IndexModel([("scene_id", ASCENDING)], name="scene"),
        _newest("object_id", name="object_newest"),
        _newest(name="newest"),
        _newest("search.region", name="region_newest"),
        _newest("search.robot", name="robot_newest"),
        _newest("search.map", name="map_newest"),
        _newest("search.terms", name="terms_newest"),
        # a text's matches counted by region and by robot from the index's keys alone (the
        # search page's facets, webui/facets.py): ~60 B a cluster at a million, since
        # neighbouring keys share their word and region and WiredTiger stores them once
        IndexModel([("search.terms", ASCENDING), ("search.region", ASCENDING),
                    ("search.robot", ASCENDING)], name="terms_region_robot"),
        # a label exactly (any annotator's): counted from the index's keys alone (COUNT_SCAN)
        _newest("search.labels", name="labels_newest"),
        # a position's Morton key with its coordinates: a box is decided and the k nearest
        # are ranked from the index alone (queries/space.py)
        IndexModel([(f"search.{key}", ASCENDING) for key in ("morton", "x", "y", "z", "time")]
                   + [("_id", ASCENDING)], name="morton_xyz"),
        # the clusters people corrected, and only those: the audit (memory/curation.py)
        IndexModel([("annotations.author", ASCENDING)], name="corrected",
                   partialFilterExpression=CORRECTED),
        # the splits people made, by the observations on either side: identity finds those
        # of a scene's clusters (memory/consolidation.py); only split clusters are in them
        IndexModel([("annotations.split_off", ASCENDING)], name="split_off", sparse=True),
        IndexModel([("annotations.apart_from", ASCENDING)], name="split_apart_from",
                   sparse=True),
        # and the field indexes a user adds (store.add_field_index): `field:<path>`
    ],
    TERMS: [IndexModel([("grams", ASCENDING)], name="grams")],
    LABELS: [IndexModel([("words", ASCENDING)], name="words")],
    OBJECTS: [
        IndexModel([("state", ASCENDING), ("last_seen", DESCENDING)], name="state_seen"),
        IndexModel([("names", ASCENDING)], name="names"),
        IndexModel([("region", ASCENDING), ("state", ASCENDING)], name="region_state"),
        IndexModel([("last_seen", DESCENDING)], name="seen"),
        # a map's objects by x then y (metres, any finite value): its places, read by its
        # consolidator (memory/places.py) and drawn on the map page
        IndexModel([("map", ASCENDING), ("x", ASCENDING), ("y", ASCENDING)], name="map_place"),
        # a map's most recently seen objects (memory/consolidation.py: unseen candidates)
        IndexModel([("map", ASCENDING), ("last_seen", DESCENDING), ("last_cluster", DESCENDING)],
                   name="map_seen"),
    ],
    CATALOGUE: [IndexModel([("map", ASCENDING), ("entry", ASCENDING)], name="map_entry"),
                IndexModel([("object_id", ASCENDING)], name="object")],
    CATALOGUE_TRACKS: [IndexModel([("map", ASCENDING)], name="map")],
    CATALOGUE_HISTORY: [IndexModel([("map", ASCENDING), ("time", DESCENDING)], name="map_time")],
    # the next scenes each map's consolidator takes: in time order, those not held
    OUTBOX: [IndexModel([("map", ASCENDING), ("held", ASCENDING), ("time", ASCENDING),
                         ("_id", ASCENDING)], name="map_next")],
    EVENTS: [
        IndexModel([("object_id", ASCENDING), ("time", DESCENDING)], name="object_time"),
        IndexModel([("scene_id", ASCENDING)], name="scene"),
        IndexModel([("time", DESCENDING)], name="time"),
        # the objects ever in a region by a time: what may be there (queries/questions.py)
        IndexModel([("region", ASCENDING), ("object_id", ASCENDING), ("time", ASCENDING)],
                   name="region_object_time"),
    ],
    JOBS: [  # ingest/jobs.py: claim the next due job; one job per kind per cluster; listings
        IndexModel([("due", ASCENDING)], name="due", sparse=True),
        IndexModel([("kind", ASCENDING), ("cluster_id", ASCENDING)], unique=True,
                   name="kind_cluster_unique"),
        IndexModel([("state", ASCENDING), ("updated", DESCENDING)], name="state_updated"),
        IndexModel([("updated", DESCENDING)], name="updated"),
    ],
    LOOKUP_CACHE: [  # ingest/lookup_cache.py: one cached result per service per hash
        IndexModel([("service", ASCENDING), ("hash", ASCENDING)], unique=True,
                   name="service_hash_unique"),
    ],
    # the indexes the GridFS spec asks for, since blobs are written without pymongo's GridFS
    GRIDFS_FILES: [IndexModel([("filename", ASCENDING), ("uploadDate", ASCENDING)])],
    GRIDFS_CHUNKS: [IndexModel([("files_id", ASCENDING), ("n", ASCENDING)], unique=True)],
}

RETIRED_INDEXES = {CLUSTERS: ("types_newest", "labels", "phash", "fields", "cells_newest_xyz"),
                   OBJECTS: ("xy_state",)}
"""Indexes earlier versions created that no query uses any more: dropped by `prepare`.
(`fields` indexed every scalar field of every annotation: ~75 entries, 2 kB a cluster of 20
annotations, half of all its index bytes, for predicates on fields hardly anyone asks about;
a field people do ask about gets an index of its own. `cells_newest_xyz` held 9 cell keys a
position, 0.6 kB; the Morton key that replaced them is one.)"""

FIELD_INDEX_PREFIX = "field:"


def field_index(path: str) -> IndexModel:
    """The index of the annotations' field at `path`: the annotation's type, then the field
    (a predicate's $elemMatch over the annotations gets bounds on both; one index serves the
    field of that name of every type), then newest first as every cluster index."""
    return _newest("annotations._type", f"annotations.{path}",
                   name=f"{FIELD_INDEX_PREFIX}{path}")

COUNTED_COLLECTIONS = (SCENES, CLUSTERS, OBJECTS, EVENTS, OUTBOX, MAPS, JOBS, LOOKUP_CACHE, TYPES,
                       TERMS, LABELS, BINARIES, GRIDFS_FILES)


def type_string(annotation: Any) -> str:
    """A readable type: `list[Annotation | Unknown]`, not `typing.List[...]` with metadata."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return type_string(args[0])
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_string(arg) for arg in args)
    if origin is typing.Literal:
        return f"Literal[{', '.join(map(repr, args))}]"
    if origin is not None:
        inner = ", ".join("..." if arg is Ellipsis else type_string(arg) for arg in args)
        return f"{getattr(origin, '__name__', str(origin))}[{inner}]"
    if annotation is type(None):
        return "None"
    return getattr(annotation, "__name__", repr(annotation))


def catalogue_entry(name: str) -> dict:
    """What the `types` collection says about a stored type name."""
    cls = class_for(name)
    if cls is None:
        return {"_id": name, "known": name in foreign_codec_names()}
    bases = [base.__name__ for base in cls.__mro__[1:] if name_of(base) is None and
             base.__name__ not in ("Model", "Typed", "BaseModel", "Identifiable", "object")]
    return {
        "_id": name,
        "known": True,
        "kind": bases[0] if bases else "type",
        "class": f"{cls.__module__}.{cls.__qualname__}",
        "aliases": aliases_of(cls),
        "doc": (cls.__doc__ or "").strip().split("\n\n")[0].replace("\n", " "),
        "fields": {
            info.alias or field: {
                "type": type_string(info.annotation), "required": info.is_required()
            }
            for field, info in cls.model_fields.items()
        },
    }
