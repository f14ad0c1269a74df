"""How scenes and clusters are laid out in MongoDB: pure functions, no I/O.

A scene is one document in `scenes` (its clusters replaced by their ids) plus one document per
cluster in `clusters`. Cluster documents carry denormalised query fields under `search` (scene
time and robot, region, position, labels, text, perceptual hash, annotation types) so that
queries never join. Both stores, sync and async, use these functions and only add the I/O.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime

from bson import ObjectId

from percept_memory.converters import (
    DecodeContext,
    EncodeContext,
    Unknown,
    decode,
    encode,
)

from .errors import NotFound
from .types import Annotation, Cluster, ImageROI, Scene, datetime_from_timestamp

SEARCH_KEY = "search"  # derived query fields, recomputed on every write
BLOBS_KEY = "_blobs"  # ids of the GridFS blobs a document refers to
SUMMARY_KEY = "summary"  # small inline summary of a scene, for list pages
DERIVED_KEYS = (SEARCH_KEY, BLOBS_KEY, SUMMARY_KEY, "time")


@dataclass
class SceneIds:
    """The ids a stored scene was given, for the caller to keep."""

    scene_id: ObjectId
    cluster_ids: list[ObjectId]
    annotation_ids: list[list[ObjectId]]


@dataclass
class Documents:
    """Everything one write stores: documents, the blobs they refer to, the type names used."""

    scene: dict | None = None
    clusters: list[dict] = field(default_factory=list)
    blobs: dict[str, bytes] = field(default_factory=dict)
    type_names: set[str] = field(default_factory=set)


def assign_ids(scene: Scene) -> SceneIds:
    """Give the scene, its clusters and their annotations ids where they have none."""
    ids = SceneIds(scene.ensure_id(), [], [])
    for cluster in scene.clusters:
        ids.cluster_ids.append(cluster.ensure_id())
        cluster.scene_id = ids.scene_id
        ids.annotation_ids.append(
            [a.ensure_id() for a in cluster.annotations if isinstance(a, Annotation)]
        )
    return ids


def scene_documents(scene: Scene, threshold: int) -> Documents:
    """The documents of a scene whose ids are assigned."""
    ctx = EncodeContext(threshold=threshold)
    out = Documents()
    for cluster in scene.clusters:
        out.clusters.append(_cluster_document(cluster, scene.timestamp, scene.robot, ctx))
    doc = encode(scene.model_copy(update={"clusters": []}), ctx)  # clusters are stored apart
    doc["clusters"] = [c.id for c in scene.clusters]
    doc["time"] = datetime_from_timestamp(scene.timestamp)
    doc[SUMMARY_KEY] = {
        "clusters": len(scene.clusters),
        "labels": sorted({label for c in out.clusters for label in c[SEARCH_KEY]["labels"]}),
        "regions": sorted({c[SEARCH_KEY]["region"] for c in out.clusters} - {None}),
    }
    _own_blobs(doc, set(ctx.blobs) - _ids_in(out.clusters))
    out.scene = doc
    out.blobs, out.type_names = ctx.blobs, ctx.type_names
    return out


def rewritten_cluster(cluster: Cluster, stored: Mapping, threshold: int) -> Documents:
    """The new document of a stored cluster, keeping its scene's time and robot."""
    ctx = EncodeContext(threshold=threshold)
    search = stored[SEARCH_KEY]
    doc = _cluster_document(cluster, search["time"], search["robot"], ctx)
    return Documents(clusters=[doc], blobs=ctx.blobs, type_names=ctx.type_names)


def _cluster_document(cluster: Cluster, timestamp: int, robot: str, ctx: EncodeContext) -> dict:
    before = set(ctx.blobs)
    doc = encode(cluster, ctx)
    doc[SEARCH_KEY] = search_fields(cluster, timestamp, robot)
    _own_blobs(doc, set(ctx.blobs) - before)
    return doc


def _own_blobs(doc: dict, blob_ids: Iterable[str]) -> None:
    blob_ids = sorted(blob_ids)
    if blob_ids:
        doc[BLOBS_KEY] = blob_ids


def _ids_in(docs: Iterable[dict]) -> set[str]:
    return {blob for doc in docs for blob in doc.get(BLOBS_KEY, ())}


def search_fields(cluster: Cluster, timestamp: int, robot: str) -> dict:
    """The denormalised query fields of a cluster."""
    annotations = [a for a in cluster.annotations if isinstance(a, Annotation)]
    roi = cluster.hypothesis_of(ImageROI)
    labels = {label.strip().casefold() for a in annotations for label in a.labels() if label}
    texts = [text for a in annotations for text in a.texts() if text]
    return {
        "time": timestamp,
        "robot": robot,
        "region": cluster.region,
        "position": list(cluster.position) if cluster.position else None,
        "labels": sorted(labels),
        "text": texts,
        "phash": roi.phash if roi else None,
        "types": sorted(
            {a.type_name for a in annotations}
            | {a.type_name for a in cluster.annotations if isinstance(a, Unknown)}
        ),
    }


def blob_ids(docs: Iterable[Mapping]) -> list[str]:
    """The blobs to fetch before decoding these documents."""
    return sorted({blob for doc in docs for blob in doc.get(BLOBS_KEY, ())})


def _stored_fields(doc: Mapping) -> dict:
    return {k: v for k, v in doc.items() if k not in DERIVED_KEYS}


def decode_cluster(doc: Mapping, blobs: Mapping[str, bytes]) -> Cluster:
    return decode(_stored_fields(doc), DecodeContext(blobs))


def decode_scene(
    doc: Mapping, cluster_docs: Iterable[Mapping], blobs: Mapping[str, bytes]
) -> Scene:
    """The scene back from its document and its clusters' documents (any order)."""
    by_id = {c["_id"]: c for c in cluster_docs}
    fields = _stored_fields(doc)
    fields["clusters"] = [_stored_fields(by_id[cid]) for cid in doc["clusters"] if cid in by_id]
    return decode(fields, DecodeContext(blobs))



GRIDFS_CHUNK_SIZE = 255 * 1024  # the GridFS default


def gridfs_documents(blob_id: str, data: bytes) -> tuple[dict, list[dict]]:
    """The `fs.files` and `fs.chunks` documents of a blob, laid out as the GridFS spec says.

    pymongo's GridFS writer refuses to run inside a transaction; writing the documents ourselves
    keeps a scene and its blobs one atomic write, and any GridFS reader can still read them.
    """
    file_doc = {
        "_id": blob_id,
        "filename": blob_id,
        "length": len(data),
        "chunkSize": GRIDFS_CHUNK_SIZE,
        "uploadDate": datetime.now(UTC).replace(microsecond=0),
    }
    chunks = [
        {"files_id": blob_id, "n": n, "data": data[start : start + GRIDFS_CHUNK_SIZE]}
        for n, start in enumerate(range(0, max(len(data), 1), GRIDFS_CHUNK_SIZE))
    ]
    return file_doc, chunks


def joined_blobs(wanted: list[str], chunk_docs: Iterable[Mapping]) -> dict[str, bytes]:
    """The blobs put back together from their GridFS chunks (in any order)."""
    parts: dict[str, list[tuple[int, bytes]]] = {blob: [] for blob in wanted}
    for chunk in chunk_docs:
        parts[chunk["files_id"]].append((chunk["n"], chunk["data"]))
    missing = [blob for blob, chunks in parts.items() if not chunks]
    if missing:
        raise NotFound("blob", ", ".join(missing))
    return {blob: b"".join(data for _, data in sorted(chunks)) for blob, chunks in parts.items()}


def appended(cluster: Cluster, annotation: Annotation) -> Cluster | None:
    """The cluster with the annotation added; None when it carries that annotation already."""
    if any(getattr(a, "id", None) == annotation.id for a in cluster.annotations):
        return None
    cluster.annotations.append(annotation)
    return cluster


def replaced(cluster: Cluster, annotation: Annotation) -> Cluster:
    """The cluster with its annotation of the same id replaced."""
    for index, existing in enumerate(cluster.annotations):
        if getattr(existing, "id", None) == annotation.id:
            cluster.annotations[index] = annotation
            return cluster
    raise NotFound("annotation", f"{annotation.id} on cluster {cluster.id}")


# Annotations and hypotheses per `_type`, over all clusters.
TYPE_COUNT_PIPELINE = [
    {"$project": {"kinds": {"$concatArrays": [
        {"$ifNull": ["$annotations._type", []]},
        {"$ifNull": ["$hypotheses._type", []]},
    ]}}},
    {"$unwind": "$kinds"},
    {"$group": {"_id": "$kinds", "count": {"$sum": 1}}},
    {"$sort": {"_id": 1}},
]
