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
JOBS = "jobs"
LOOKUP_CACHE = "lookup_cache"
TYPES = "types"
GRIDFS_FILES = "fs.files"
GRIDFS_CHUNKS = "fs.chunks"

INDEXES: dict[str, list[IndexModel]] = {
    SCENES: [
        IndexModel([("robot", ASCENDING), ("timestamp", ASCENDING)], unique=True,
                   name="robot_time_unique"),
        IndexModel([("timestamp", DESCENDING)], name="time"),
    ],
    CLUSTERS: [
        IndexModel([("scene_id", ASCENDING)], name="scene"),
        IndexModel([("object_id", ASCENDING), ("search.time", DESCENDING)], name="object_time"),
        IndexModel([("search.time", DESCENDING)], name="time"),
        IndexModel([("search.region", ASCENDING), ("search.time", DESCENDING)],
                   name="region_time"),
        IndexModel([("search.labels", ASCENDING)], name="labels"),
        IndexModel([("search.types", ASCENDING)], name="types"),
        IndexModel([("search.phash", ASCENDING)], name="phash", sparse=True),
    ],
    OBJECTS: [
        IndexModel([("state", ASCENDING), ("last_seen", DESCENDING)], name="state_seen"),
        IndexModel([("names", ASCENDING)], name="names"),
        IndexModel([("region", ASCENDING), ("state", ASCENDING)], name="region_state"),
    ],
    EVENTS: [
        IndexModel([("object_id", ASCENDING), ("time", DESCENDING)], name="object_time"),
        IndexModel([("scene_id", ASCENDING)], name="scene"),
        IndexModel([("time", DESCENDING)], name="time"),
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

COUNTED_COLLECTIONS = (SCENES, CLUSTERS, OBJECTS, EVENTS, JOBS, LOOKUP_CACHE, TYPES, GRIDFS_FILES)


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
