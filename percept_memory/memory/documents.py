"""How scenes and clusters are laid out in MongoDB: pure functions, no I/O.

A scene is one document in `scenes` (its clusters replaced by their ids) plus one document per
cluster in `clusters`. Cluster documents carry denormalised query fields under `search` (scene
time and robot, region, position, labels, text, annotation types) so that queries never join.
Both stores, sync and async, use these functions and only add the I/O.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

import bson
from bson import ObjectId
from bson.raw_bson import RawBSONDocument
from pydantic import ValidationError

from percept_memory.converters import (
    BLOB_KEY,
    TYPE_KEY,
    DecodeContext,
    EncodeContext,
    Unknown,
    class_for,
    decode,
    encode,
    name_of,
)

from . import search_keys
from .errors import NotFound, SceneExists, TypeHookFailed, problems_line
from .schema import BINARIES, GRIDFS_CHUNKS, GRIDFS_FILES, LABELS, TERMS
from .types import Annotation, Cluster, Scene, datetime_from_timestamp
from .types.curation import in_force

SEARCH_KEY = "search"  # derived query fields, recomputed on every write
BLOBS_KEY = "_blobs"  # ids of the GridFS blobs a document refers to
SUMMARY_KEY = "summary"  # small inline summary of a scene, for list pages
# how many of a cluster's annotations came with its scene: the evidence identity decides on,
# the same live and in a rebuild, whatever enrichment appended since (memory/pipeline.py)
ARRIVED_KEY = "arrived"
DERIVED_KEYS = (SEARCH_KEY, BLOBS_KEY, SUMMARY_KEY, ARRIVED_KEY, "time")


@dataclass
class SceneIds:
    """The ids of a stored scene, for the caller to keep. `created` is False when the scene
    (same robot, same timestamp) was stored before and these are the ids it was given then."""

    scene_id: ObjectId
    cluster_ids: list[ObjectId]
    annotation_ids: list[list[ObjectId]]
    created: bool = True


@dataclass
class Documents:
    """Everything one write stores: documents, the blobs they refer to, the type names used."""

    scenes: list[Mapping] = field(default_factory=list)  # as BSON when a whole scene is written
    clusters: list[Mapping] = field(default_factory=list)
    blobs: dict[str, bytes] = field(default_factory=dict)
    type_names: set[str] = field(default_factory=set)
    terms: set[str] = field(default_factory=set)  # the vocabulary: words to spell-correct to
    labels: set[str] = field(default_factory=set)  # and labels to find by their words
    outbox: list[dict] = field(default_factory=list)  # the stages each new scene awaits

    def add(self, other: Documents) -> None:
        """Take in another write's documents (the two are written as one)."""
        self.scenes += other.scenes
        self.clusters += other.clusters
        self.outbox += other.outbox
        self.blobs.update(other.blobs)
        self.type_names |= other.type_names
        self.terms |= other.terms
        self.labels |= other.labels

    def encode(self, value: Scene | Cluster, threshold: int) -> dict:
        """The document of one object. Each document lists the blobs it refers to itself,
        even when another document of the write holds the same (content-addressed) bytes."""
        ctx = EncodeContext(threshold=threshold)
        doc = encode(value, ctx)
        if ctx.blobs:
            doc[BLOBS_KEY] = sorted(ctx.blobs)
            self.blobs.update(ctx.blobs)
        self.type_names |= ctx.type_names
        return doc


IdSnapshot = list[tuple[Any, str, Any]]


@dataclass
class PreparedWrite:
    """Scenes ready to be written: their ids (stored or assigned), the documents of the new
    ones (`fresh`), and the ids each scene had before, to undo the assignment for a scene that
    turns out to be stored already."""

    scenes: Sequence[Scene]
    fresh: list[Scene]
    results: list[SceneIds]
    documents: Documents
    before: list[IdSnapshot]


# --- what the stores' callers hand in: a mistake is a TypeError naming it, not one from deep
# inside (a dict where a Scene belongs had no attribute `id`)


def as_id(value: Any, what: str) -> ObjectId:
    """An id argument: an ObjectId, or its 24 hexadecimal digits."""
    if isinstance(value, ObjectId):
        return value
    if isinstance(value, str) and ObjectId.is_valid(value):
        return ObjectId(value)
    raise TypeError(f"{what}: expected an ObjectId or its 24 hexadecimal digits, got "
                    f"{value!r:.60}")


def checked(values: Sequence, kinds: type | tuple[type, ...], what: str) -> None:
    """A TypeError unless each value is of these kinds (a dict is not a Scene:
    Scene.model_validate makes one of it)."""
    for value in values:
        if not isinstance(value, kinds):
            names = " or ".join(k.__name__ for k in (kinds if isinstance(kinds, tuple)
                                                     else (kinds,)))
            raise TypeError(f"{what}: expected {names}, got {type(value).__name__}")


def prepared(scenes: Sequence[Scene], stored: dict, threshold: int) -> PreparedWrite:
    """Assign ids and encode the scenes not in `stored` (their key -> SceneIds). Two
    different scenes under one (robot, timestamp) refuse the write (SceneExists), as one
    already stored does (store.py): the second would be lost."""
    checked(scenes, Scene, "scenes")
    refuse_repeats(scenes)
    before = [id_snapshot(scene) for scene in scenes]
    fresh, results = partition(scenes, stored)
    return PreparedWrite(scenes, fresh, results, scene_documents(fresh, threshold), before)


def joined(writes: Sequence[PreparedWrite]) -> PreparedWrite:
    """Writes prepared one after the other, as one."""
    whole = PreparedWrite([], [], [], Documents(), [])
    for write in writes:
        whole.scenes += write.scenes  # type: ignore[operator]
        whole.fresh += write.fresh
        whole.results += write.results
        whole.documents.add(write.documents)
        whole.before += write.before
    return whole


def id_snapshot(scene: Scene) -> IdSnapshot:
    """Every id assign_ids may set, with its value now."""
    items: IdSnapshot = [(scene, "id", scene.id)]
    for cluster in scene.clusters:
        items += [(cluster, "id", cluster.id), (cluster, "scene_id", cluster.scene_id)]
        items += [(a, "id", a.id) if isinstance(a, Annotation) else (a, "fields", dict(a.fields))
                  for a in cluster.annotations]
    return items


def undo_ids(write: PreparedWrite, stored: dict) -> None:
    """Put back the ids of the scenes found stored: their objects keep no ids that were never
    written."""
    for scene, snapshot in zip(write.scenes, write.before, strict=True):
        if scene_key(scene) in stored:
            for obj, field_name, value in snapshot:
                setattr(obj, field_name, value)


def assign_ids(scene: Scene) -> SceneIds:
    """Give the scene, its clusters and their annotations ids where they have none."""
    ids = SceneIds(scene.ensure_id(), [], [])
    for cluster in scene.clusters:
        ids.cluster_ids.append(cluster.ensure_id())
        cluster.scene_id = ids.scene_id
        ids.annotation_ids.append([annotation_id(a) for a in cluster.annotations])
    return ids


def annotation_id(annotation: Annotation | Unknown):
    """The id of an annotation, assigned where it has none: a foreign (Unknown) one's `_id`
    too, so that each annotation a scene is stored with is named by the id at its place."""
    if isinstance(annotation, Unknown):
        if annotation.fields.get("_id") is None:  # (none, or null)
            annotation.fields["_id"] = ObjectId()
        return annotation.fields["_id"]
    return annotation.ensure_id()


def scene_documents(scenes: Iterable[Scene], threshold: int) -> Documents:
    """The documents of scenes whose ids are assigned, for one write, as BSON at once: their
    dicts are freed as soon as they are built, instead of being walked by the garbage
    collector again and again while a batch waits for its commit (a fifth of ingest time)."""
    out = Documents()
    for scene in scenes:
        clusters = [
            _cluster_document(c, scene.timestamp, scene.robot, scene.map, threshold, out)
            for c in scene.clusters
        ]
        doc = out.encode(scene.model_copy(update={"clusters": []}), threshold)  # stored apart
        doc["clusters"] = [c.id for c in scene.clusters]
        doc["time"] = datetime_from_timestamp(scene.timestamp)
        doc[SUMMARY_KEY] = scene_summary(doc, clusters)
        out.scenes.append(as_bson(doc))
        out.clusters.extend(map(as_bson, clusters))
        out.outbox.append(outbox_entry(scene.id, scene.map, scene.timestamp))
    return out


def outbox_entry(scene_id: ObjectId, map_name: str, timestamp: int, done=()) -> dict:
    """A scene's entry in the pipeline's outbox, written in the scene's own transaction: the
    after-store stages it still awaits (all but `done`), taken in time order per map."""
    return {"_id": scene_id, "map": map_name, "time": timestamp, "done": list(done),
            "attempts": 0, "held": False, "due": None, "error": None}


SUMMARY_PROJECTION = {"log.source": 1, "annotations.source": 1, "annotations._type": 1,
                      "search.labels": 1, "search.region": 1, "search.types": 1}
"""What scene_summary reads of a scene document and of its cluster documents."""
SUMMARY_SETS = ("labels", "regions", "annotators", "types")
RECOUNT = "recount"  # summary_change: the scene's summary must be worked out again


def scene_summary(scene_doc: Mapping, cluster_docs: Sequence[Mapping]) -> dict:
    """The small inline summary of a scene: what its list row shows (cluster count, labels,
    regions) and what the scene log filters by, each an indexed array (schema.py): its
    regions, its annotators (the sources of its log lines and of all its annotations) and the
    annotation types on it or on its clusters."""
    scene_annotations = scene_doc.get("annotations", ())
    own = {"labels": set(), "regions": set(), "types": {a["_type"] for a in scene_annotations},
           "annotators": _sources([*scene_annotations, *scene_doc.get("log", ())])}
    parts = [own, *map(_summary_sets, cluster_docs)]
    return {"clusters": len(cluster_docs),
            **{key: sorted(set().union(*(part[key] for part in parts))) for key in SUMMARY_SETS}}


def summary_change(before: Mapping, after: Mapping) -> list[dict] | str | None:
    """How rewriting a cluster document changes its scene's summary: None (not at all), an
    update pipeline adding the values it gained (the usual case: annotations appended), or
    RECOUNT when it lost some, which only scene_summary over all the clusters can tell."""
    old, new = _summary_sets(before), _summary_sets(after)
    if old == new:
        return None
    if any(not old[key] <= new[key] for key in SUMMARY_SETS):
        return RECOUNT
    return [{"$set": {f"{SUMMARY_KEY}.{key}": {"$sortArray": {"input": {"$setUnion": [
        {"$ifNull": [f"${SUMMARY_KEY}.{key}", []]}, {"$literal": sorted(new[key])}]},
        "sortBy": 1}} for key in SUMMARY_SETS}}]


def _summary_sets(cluster_doc: Mapping) -> dict[str, set[str]]:
    search = cluster_doc[SEARCH_KEY]
    return {"labels": set(search["labels"]), "regions": {search["region"]} - {None},
            "annotators": _sources(cluster_doc.get("annotations", ())),
            "types": set(search["types"])}


def _sources(annotations: Iterable[Mapping]) -> set[str]:
    return {a.get("source") for a in annotations} - {None, ""}


def rewritten_cluster(cluster: Cluster, stored: Mapping, threshold: int) -> Documents:
    """The new document of a stored cluster, keeping its scene's time, robot and map (none
    for data stored before clusters knew it, until `reindex`)."""
    out = Documents()
    search = stored[SEARCH_KEY]
    doc = _cluster_document(cluster, search["time"], search["robot"], search.get("map"),
                            threshold, out)
    doc[ARRIVED_KEY] = arrived(stored)
    out.clusters.append(doc)
    return out


def arrived(cluster_doc: Mapping) -> int:
    """How many of the cluster's annotations came with its scene (all, for data stored before
    this was recorded, and for a cluster's own data that leaves it unset)."""
    count = cluster_doc.get(ARRIVED_KEY)
    return len(cluster_doc.get("annotations", ())) if count is None else count


def as_bson(doc: dict) -> RawBSONDocument:
    """A document encoded once: pymongo sends its bytes as they are."""
    return RawBSONDocument(bson.encode(doc))


def _cluster_document(cluster: Cluster, timestamp: int, robot: str, map_name: str | None,
                      threshold: int, out: Documents) -> dict:
    doc = out.encode(cluster, threshold)
    doc[ARRIVED_KEY] = len(cluster.annotations_arrived())
    doc[SEARCH_KEY] = search = search_fields(cluster, timestamp, robot, map_name)
    out.terms.update(filter(search_keys.misspellable, search["terms"]))
    out.labels.update(label for label in search["labels"] if not search_keys.one_word(label))
    return doc


def stored_ids(scene_doc: Mapping, cluster_docs: Iterable[Mapping]) -> SceneIds:
    """The ids of a scene stored before, from its document and its clusters' `annotations._id`."""
    annotations = {c["_id"]: [a["_id"] for a in c.get("annotations", []) if "_id" in a]
                   for c in cluster_docs}
    cluster_ids = list(scene_doc["clusters"])
    return SceneIds(
        scene_doc["_id"], cluster_ids, [annotations.get(c, []) for c in cluster_ids], False
    )


def stored_by_key(scene_docs: Iterable[Mapping], cluster_docs: Iterable[Mapping]) -> dict:
    """(robot, timestamp) -> SceneIds of stored scenes."""
    cluster_docs = list(cluster_docs)
    return {scene_key(doc): stored_ids(doc, cluster_docs) for doc in scene_docs}


# what a scene's or a cluster's document holds that is not what it saw: ids, the links
# consolidation makes, keys derived from it (and grown by what enrichment adds later), and
# the log (how long its annotators took, which a scene made again, re-imported, measures anew)
NOT_CONTENT = {"_id", "scene_id", "object_id", "clusters", "search", "summary", "log"}


def differing(write: PreparedWrite, stored_scenes: Iterable[Mapping],
              stored_clusters: Iterable[Mapping]) -> list[tuple[str, int]]:
    """The keys of the scenes of `write` to be written whose (robot, timestamp) a stored scene
    has, with other content: not the same scene sent again. A stored cluster is compared by
    the annotations it arrived with (enrichment and people append others)."""
    clusters = {doc["_id"]: doc for doc in stored_clusters}
    stored = {scene_key(doc): _content(doc, [clusters[c] for c in doc["clusters"]
                                             if c in clusters])
              for doc in stored_scenes}
    new_clusters = {doc["_id"]: doc for doc in map(_plain, write.documents.clusters)}
    found = []
    for doc in map(_plain, write.documents.scenes):
        key = scene_key(doc)
        if key in stored and stored[key] != _content(
                doc, [new_clusters[c] for c in doc["clusters"]]):
            found.append(key)
    return found


def _plain(doc: Mapping) -> dict:
    """A document as the store reads it back (times aware of their UTC, as CLIENT_OPTIONS)."""
    if isinstance(doc, RawBSONDocument):
        return bson.decode(doc.raw, codec_options=bson.CodecOptions(tz_aware=True))
    return dict(doc)


def _content(scene: Mapping, clusters: list[Mapping]) -> tuple:
    def said(cluster: Mapping) -> dict:
        doc = _without_ids(cluster)
        doc["annotations"] = doc.get("annotations", [])[:arrived(cluster)]
        return doc
    return _without_ids(scene), [said(c) for c in clusters]


def _without_ids(value: Any, top: bool = True) -> Any:
    if isinstance(value, Mapping):
        return {k: _without_ids(v, False) for k, v in value.items()
                if k != "_id" and not (top and k in NOT_CONTENT)}
    if isinstance(value, list):
        return [_without_ids(v, False) for v in value]
    return value


def refuse_repeats(scenes: Sequence[Scene]) -> None:
    """SceneExists for a (robot, timestamp) that two scenes of the batch have with other
    content (as `differing` compares: ids, search keys, summary and log aside); the same
    scene twice is fine (written once)."""
    first: dict[tuple[str, int], Scene] = {}
    for scene in scenes:
        key = scene_key(scene)
        seen = first.setdefault(key, scene)
        if seen is not scene and _model_content(seen) != _model_content(scene):
            raise SceneExists(*key, in_batch=True)


def _model_content(scene: Scene) -> tuple:
    dump = scene.model_dump(mode="json", by_alias=True)
    return _content(dump, dump["clusters"])


def partition(scenes: Iterable[Scene], stored: dict) -> tuple[list[Scene], list[SceneIds]]:
    """The scenes still to write, and the ids of every scene in order: stored ones keep the
    ids they have, new ones get ids assigned (a scene twice in one batch is written once)."""
    fresh: list[Scene] = []
    results: list[SceneIds] = []
    first: dict[tuple[str, int], SceneIds] = {}
    for scene in scenes:
        key = scene_key(scene)
        if key in stored:
            results.append(stored[key])
        elif key in first:
            results.append(replace(first[key], created=False))
        else:
            first[key] = assign_ids(scene)
            fresh.append(scene)
            results.append(first[key])
    return fresh, results


STORED_IDS_PROJECTION = {"robot": 1, "timestamp": 1, "clusters": 1}


def stored_query(keys: Iterable[tuple[str, int]]) -> dict:
    """The filter finding the stored scenes with these (robot, timestamp) keys."""
    return {"$or": [{"robot": robot, "timestamp": time} for robot, time in sorted(set(keys))]}


def scene_key(scene: Scene | Mapping) -> tuple[str, int]:
    """What identifies a scene: the robot that took it and when."""
    if isinstance(scene, Mapping):
        return scene["robot"], scene["timestamp"]
    return scene.robot, scene.timestamp


def search_fields(cluster: Cluster, timestamp: int, robot: str, map_name: str | None) -> dict:
    """The denormalised query fields of a cluster (its scene's time, robot and map: positions
    of two maps are in two frames)."""
    annotations = [a for a in cluster.annotations if isinstance(a, Annotation)]
    said = in_force(annotations)  # a correction taken back is no longer found by its label
    labels = {search_keys.normal_label(label) for a in said
              for label in _hook(a, "labels")} - {""}
    texts = [text for a in said for text in _hook(a, "texts") if text]
    position = cluster.position
    return {
        "time": timestamp,
        "robot": robot,
        "map": map_name,
        "region": cluster.region,
        **search_keys.place(position),
        "labels": sorted(labels),
        "text": texts,
        "terms": sorted({w for t in (*labels, *texts) for w in search_keys.words(t)}),
        "types": sorted(
            {a.type_name for a in annotations}
            | {a.type_name for a in cluster.annotations if isinstance(a, Unknown)}
        ),
    }


def _hook(annotation: Annotation, name: str) -> list[str]:
    """What a type's labels() or texts() says of an annotation: a type's own code, which may
    fail on it (TypeHookFailed names the type and why, not a server error)."""
    try:
        return list(getattr(annotation, name)())
    except Exception as error:
        raise TypeHookFailed(f"{annotation.type_name}.{name}() failed on annotation "
                             f"{annotation.id}: {type(error).__name__}: {error}") from None


def vocabulary_documents(terms: Iterable[str], labels: Iterable[str]) -> dict[str, list[dict]]:
    """The `terms` (with trigrams, to find misspelt words' neighbours) and `labels` (with
    their words, to find objects by any word of a name) documents of these words."""
    return {
        TERMS: [{"_id": t, "grams": search_keys.trigrams(t)} for t in sorted(terms)],
        LABELS: [{"_id": label, "words": sorted(set(search_keys.words(label)))}
                 for label in sorted(labels)],
    }


def blob_ids(docs: Iterable[Mapping]) -> list[str]:
    """The blobs to fetch before decoding these documents: those they refer to as read, so
    that a document read without its pixels (a projection) fetches none of them."""
    return sorted({blob for doc in docs for blob in _references(doc)})


def _references(value: dict | list) -> Iterable[str]:
    """(Only containers are descended into: a descriptor's thousand numbers are not.)"""
    if isinstance(value, dict) and BLOB_KEY in value:
        yield value[BLOB_KEY]
        return
    for item in value.values() if isinstance(value, dict) else value:
        if isinstance(item, dict | list):
            yield from _references(item)


def _stored_fields(doc: Mapping) -> dict:
    return {k: v for k, v in doc.items() if k not in DERIVED_KEYS}


def _cluster_fields(doc: Mapping) -> dict:
    """A cluster's stored fields, with how many annotations arrived when others came later."""
    fields = _stored_fields(doc)
    if (count := arrived(doc)) < len(doc.get("annotations", ())):
        fields[ARRIVED_KEY] = count
    return fields


def fitted(cluster: Cluster) -> tuple[Cluster, list[str]]:
    """The cluster with each annotation of a registered type checked against its class, and
    what did not fit. Reading trusts what was validated when it was stored; one stored before
    its class was imported (as another program's) was not, and may not fit: it is kept as
    stored, an Unknown saying why, not read into a class whose labels() it would break."""
    kept, problems, changed = [], [], False
    for annotation in cluster.annotations:
        if isinstance(annotation, Annotation):
            kind = type(annotation)
            try:
                valid = kind.model_validate({k: getattr(annotation, k) for k in kind.model_fields})
            except ValidationError as error:
                problem = f"{name_of(kind)}: {problems_line(error)}"
                annotation = Unknown.model_construct(type_name=name_of(kind),
                                                     fields=encode(annotation), problem=problem)
                problems.append(problem)
            else:  # as validating makes it (a number stored as "1500" read as 1500.0)
                if valid != annotation:
                    valid.keep_unknown_fields(annotation.unknown_fields() or {})
                    annotation, changed = valid, True
        elif isinstance(annotation, Unknown) and (kind := class_for(annotation.type_name)):
            try:  # (stored in a form JSON takes and reading does not: an array as a list)
                annotation = kind.model_validate({k: v for k, v in annotation.fields.items()
                                                  if k != TYPE_KEY})
                changed = True
            except ValidationError as error:
                problems.append(f"{annotation.type_name}: {problems_line(error)}")
        kept.append(annotation)
    fitting = cluster.model_copy(update={"annotations": kept}) if problems or changed else cluster
    return fitting, problems


def decode_cluster(doc: Mapping, blobs: Mapping[str, bytes]) -> Cluster:
    return decode(_cluster_fields(doc), DecodeContext(blobs))


def decode_scene(
    doc: Mapping, cluster_docs: Iterable[Mapping], blobs: Mapping[str, bytes]
) -> Scene:
    """The scene back from its document and its clusters' documents (any order)."""
    by_id = {c["_id"]: c for c in cluster_docs}
    fields = _stored_fields(doc)
    fields["clusters"] = [_cluster_fields(by_id[cid]) for cid in doc["clusters"] if cid in by_id]
    return decode(fields, DecodeContext(blobs))



GRIDFS_CHUNK_SIZE = 255 * 1024  # the GridFS default


def blob_homes(blobs: Mapping[str, bytes]) -> dict[str, list[str]]:
    """Where each blob is kept: a document of its own in `binaries` (crops, masks, most
    images: one index entry, read by id), or chunked as a GridFS file above a chunk's size."""
    homes: dict[str, list[str]] = {}
    for blob_id, data in blobs.items():
        homes.setdefault(BINARIES if len(data) <= GRIDFS_CHUNK_SIZE else GRIDFS_FILES,
                         []).append(blob_id)
    return homes


def blob_writes(blobs: Mapping[str, bytes], stored: Iterable[str]) -> dict[str, list[dict]]:
    """The documents to insert, per collection in the order to insert them, for the blobs not
    `stored` yet (content ids: a blob stored once is never written again): one insert per
    collection for a whole write, however many crops it holds."""
    writes: dict[str, list[dict]] = {BINARIES: [], GRIDFS_CHUNKS: [], GRIDFS_FILES: []}
    for blob_id in sorted(blobs.keys() - set(stored)):
        data = blobs[blob_id]
        if len(data) <= GRIDFS_CHUNK_SIZE:
            writes[BINARIES].append({"_id": blob_id, "data": data})
        else:  # a GridFS file is complete once its `fs.files` document is there
            file_doc, chunks = gridfs_documents(blob_id, data)
            writes[GRIDFS_CHUNKS] += chunks
            writes[GRIDFS_FILES].append(file_doc)
    return {name: documents for name, documents in writes.items() if documents}


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


def appended(cluster: Cluster, annotations: Sequence[Annotation]) -> Cluster | None:
    """The cluster with those of the annotations it does not carry yet (by id) added; None
    when it carries them all already."""
    present = {getattr(a, "id", None) for a in cluster.annotations}
    new = [a for a in annotations if a.id not in present]
    if not new:
        return None
    cluster.annotations.extend(new)
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
