"""Corrections by people (memory/curation.py) on a day of the kitchen week: names follow a
relabel at once and go back on undo, a rejection takes the cluster out of the belief through a
rebuild, the belief built live equals the one rebuilt, exports use the corrected labels."""

from __future__ import annotations

import io
import json
import zipfile

import pytest
from bson import ObjectId

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import memory_pipeline
from percept_memory.memory import curation
from percept_memory.memory.consolidation import ANY_SPLIT, naming_splits
from percept_memory.memory.errors import NotFound
from percept_memory.memory.pipeline import request_rebuild
from percept_memory.memory.schema import EVENTS, MAPS, OBJECTS
from percept_memory.memory.types import (
    Classification,
    DifferentObject,
    Rejection,
    Relabel,
    SameObject,
    Undo,
)
from percept_memory.memory.types.curation import verdict
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.export.model import ExportQuery
from percept_memory.queries.export.run import Export

from .conftest import ingest_consolidated


@pytest.fixture(scope="module")
def memory(store):
    ingest_consolidated(store, kitchen_week.generate(days=1).scenes)
    return store


def settle(store) -> None:
    pipeline = memory_pipeline(store)
    pipeline.drain(timeout=300)
    assert not pipeline.pending()


def a_classified_cluster(store, skip: int = 0):
    doc = store.clusters.find({"object_id": {"$ne": None},
                               "annotations._type": "pm.annotation.Classification",
                               "annotations.author": {"$exists": False}}).sort("_id", 1).skip(
        skip).limit(1).next()
    return store.get_cluster(doc["_id"])


def beliefs(store) -> dict:
    """Each cluster's object, as the names of that object (object ids are made afresh by a
    rebuild), and every object's names and observations."""
    objects = {o["_id"]: (tuple(o["names"]), o["observations"])
               for o in store.db[OBJECTS].find()}
    return {c["_id"]: objects.get(c.get("object_id"))
            for c in store.clusters.find({}, {"object_id": 1})}


def test_a_relabel_names_the_object_at_once_and_an_undo_takes_it_back(memory):
    cluster = a_classified_cluster(memory)
    before = memory.db[OBJECTS].find_one({"_id": cluster.object_id})
    said = list(cluster.annotations)
    made = curation.relabel(memory, cluster.id, "Grandma's teapot", author="ana")
    assert isinstance(made, Relabel) and made.author == "ana" and made.time > 0
    after = memory.db[OBJECTS].find_one({"_id": cluster.object_id})
    assert after["name"] == "grandma's teapot" != before["name"]
    stored = memory.get_cluster(cluster.id)
    assert stored.annotations[:len(said)] == said  # what annotators said is kept as it was
    assert stored.annotations[-1] == made
    assert memory.clusters.find_one({"_id": cluster.id, "search.terms": "teapot"})

    taken_back = curation.undo(memory, cluster.id, made.id, author="bo")
    assert isinstance(taken_back, Undo) and taken_back.undoes == made.id
    restored = memory.db[OBJECTS].find_one({"_id": cluster.object_id})
    assert (restored["names"], restored["label_weights"]) == (before["names"],
                                                              before["label_weights"])
    assert not memory.clusters.find_one({"_id": cluster.id, "search.terms": "teapot"})
    rows = curation.audit(memory)
    assert [(r["kind"], r["author"]) for r in rows[:2]] == [("undo", "bo"), ("relabel", "ana")]
    assert rows[1]["undone_by"]["author"] == "bo" and rows[1]["label"] == "Grandma's teapot"
    assert rows[0]["undoes"] == made.id and rows[0]["cluster_id"] == cluster.id


def test_a_rejection_takes_the_cluster_out_of_the_belief_until_undone(memory):
    cluster = a_classified_cluster(memory, skip=3)
    map_name = memory.scenes.find_one({"_id": cluster.scene_id})["map"]
    made = curation.reject(memory, cluster.id, author="ana", reason="a reflection")
    assert isinstance(made, Rejection)
    assert memory.db[MAPS].find_one({"_id": map_name})["rebuild"] is True  # same transaction
    settle(memory)
    assert memory.clusters.find_one({"_id": cluster.id}).get("object_id") is None
    assert not memory.db[EVENTS].find_one({"scene_id": cluster.scene_id,
                                           "cluster_id": cluster.id})
    with pytest.raises(NotFound, match="no object of the cluster .*: a person rejected it"):
        QueryEngine(memory).where_is(str(cluster.id))  # (not "no object or cluster")
    curation.undo(memory, cluster.id, made.id, author="ana")
    settle(memory)
    assert memory.clusters.find_one({"_id": cluster.id}).get("object_id") is not None
    assert curation.counts(memory)["reject"] >= 1


def two_objects(store, skip: int = 0) -> tuple:
    """The latest clusters of two objects of one map, not corrected, seen in two scenes (one
    scene's observations are never one object)."""
    first, *others = (store.db[OBJECTS].find({"map": {"$exists": True}}).sort("_id", 1)
                      .skip(skip))
    scene = store.clusters.find_one({"_id": first["last_cluster"]})["scene_id"]
    second = next(o for o in others if store.clusters.find_one(
        {"_id": o["last_cluster"]})["scene_id"] != scene)
    assert first["map"] == second["map"]
    return first["last_cluster"], second["last_cluster"]


def test_a_merge_makes_two_objects_one_until_undone(memory):
    a, b = two_objects(memory, skip=2)
    objects = memory.db[OBJECTS].count_documents({})
    names = {n for c in (a, b) for n in memory.db[OBJECTS].find_one(
        {"_id": memory.clusters.find_one({"_id": c})["object_id"]})["label_weights"]}
    made = curation.merge(memory, a, b, author="ana")
    assert isinstance(made, SameObject) and made.other in (a, b)
    settle(memory)
    linked = {memory.clusters.find_one({"_id": c})["object_id"] for c in (a, b)}
    assert len(linked) == 1 and memory.db[OBJECTS].count_documents({}) == objects - 1
    (one,) = linked
    assert set(memory.db[OBJECTS].find_one({"_id": one})["label_weights"]) == names
    assert curation.audit(memory, 1)[0]["kind"] == "merge"
    later = b if made.other == a else a  # the correction is stored on the later cluster
    curation.undo(memory, later, made.id, author="ana")
    settle(memory)
    assert len({memory.clusters.find_one({"_id": c})["object_id"] for c in (a, b)}) == 2
    assert memory.db[OBJECTS].count_documents({}) == objects


def test_a_merge_with_itself_or_an_unknown_cluster_is_refused(memory):
    a, _ = two_objects(memory)
    with pytest.raises(curation.NotCorrectable, match="itself"):
        curation.merge(memory, a, a, author="ana")
    with pytest.raises(NotFound):
        curation.merge(memory, a, ObjectId(), author="ana")


def test_a_merge_of_two_observations_of_one_scene_is_refused(memory):
    scene = next(memory.clusters.aggregate([
        {"$group": {"_id": "$scene_id", "clusters": {"$push": "$_id"}}},
        {"$match": {"clusters.1": {"$exists": True}}}, {"$limit": 1}]))
    a, b = scene["clusters"][:2]
    before = list(memory.clusters.find({"_id": {"$in": [a, b]}}, {"annotations": 1}))
    with pytest.raises(curation.NotCorrectable, match="one scene"):
        curation.merge(memory, a, b, author="ana")
    assert list(memory.clusters.find({"_id": {"$in": [a, b]}}, {"annotations": 1})) == before


def observed_often(store, skip: int = 0) -> tuple:
    """An object seen in many scenes, none of its clusters corrected, and its clusters in
    time order."""
    objects = store.db[OBJECTS].find({"observations": {"$gte": 6}}).sort("_id", 1)
    for obj in objects:
        clusters = [c["_id"] for c in store.clusters.find(
            {"object_id": obj["_id"]}, {"annotations": 1, "search.time": 1}).sort(
            "search.time", 1) if not any("author" in a for a in c["annotations"])]
        if len(clusters) == obj["observations"]:
            if skip == 0:
                return obj["_id"], clusters
            skip -= 1
    raise AssertionError("no object seen often enough")


def objects_of(store, clusters) -> list:
    return [store.clusters.find_one({"_id": c})["object_id"] for c in clusters]


@pytest.mark.parametrize("pick", [
    lambda clusters: clusters[len(clusters) // 2:],  # the latest half
    lambda clusters: clusters[1::2],  # every other one: against the object's own likeness
    lambda clusters: clusters[:2],  # the first observations
])
def test_a_split_keeps_the_two_sides_apart_after_a_rebuild_until_undone(memory, pick):
    object_id, clusters = observed_often(memory)
    split_off = pick(clusters)
    kept = [c for c in clusters if c not in split_off]
    objects = memory.db[OBJECTS].count_documents({})
    made = curation.split(memory, object_id, split_off, author="ana")
    assert isinstance(made, DifferentObject)
    assert (made.split_off, made.apart_from) == (split_off, kept)  # both in time order
    assert made.id in {a.id for a in memory.get_cluster(split_off[0]).annotations}
    settle(memory)
    for _ in ("live", "rebuilt"):
        assert not set(objects_of(memory, split_off)) & set(objects_of(memory, kept))
        assert memory.db[OBJECTS].count_documents({}) > objects
        request_rebuild(memory)  # as `pmem reconsolidate` does
        settle(memory)
    (row,) = curation.audit(memory, 1)
    assert (row["kind"], row["split_off"], row["apart_from"]) == ("split", split_off, kept)
    curation.undo(memory, split_off[0], made.id, author="ana")
    settle(memory)
    assert len(set(objects_of(memory, clusters))) == 1
    assert memory.db[OBJECTS].count_documents({}) == objects


def test_identity_finds_a_scenes_splits_from_their_indexes(memory):
    scene = memory.scenes.find_one()
    plan = json.dumps(memory.clusters.find(naming_splits(scene["clusters"])).explain(),
                      default=str)
    assert "COLLSCAN" not in plan
    assert '"split_off"' in plan and '"split_apart_from"' in plan
    # and whether there is any split at all, asked once per batch, from the sparse index
    plan = json.dumps(memory.clusters.find(ANY_SPLIT).limit(1).explain(), default=str)
    assert "COLLSCAN" not in plan and '"split_off"' in plan


def test_no_merge_joins_what_a_split_keeps_apart(memory):
    object_id, clusters = observed_often(memory, skip=1)
    split_off, kept = clusters[1::2], clusters[::2]
    curation.split(memory, object_id, split_off, author="bo")
    curation.merge(memory, split_off[-1], kept[0], author="cy")  # said after: the split stands
    settle(memory)
    assert not set(objects_of(memory, split_off)) & set(objects_of(memory, kept))


@pytest.mark.parametrize("which, message", [
    (lambda clusters, other: [], "clusters: name 1 to"),
    (lambda clusters, other: clusters, "all the object's observations"),
    (lambda clusters, other: [clusters[0], other], "is not an observation of object"),
])
def test_a_split_that_cannot_be_is_refused_and_writes_nothing(memory, which, message):
    object_id, clusters = observed_often(memory, skip=2)
    other = memory.clusters.find_one({"object_id": {"$nin": [object_id, None]}})["_id"]
    corrected = curation.counts(memory)["clusters"]
    with pytest.raises(curation.NotCorrectable, match=message):
        curation.split(memory, object_id, which(clusters, other), author="ana")
    assert curation.counts(memory)["clusters"] == corrected
    with pytest.raises(NotFound):
        curation.split(memory, ObjectId(), clusters[:1], author="ana")


def test_the_belief_with_corrections_built_live_equals_the_one_rebuilt(memory):
    relabelled = a_classified_cluster(memory, skip=5)
    curation.relabel(memory, relabelled.id, "teapot", author="ana")
    curation.reject(memory, a_classified_cluster(memory, skip=8).id, author="bo")
    curation.merge(memory, *two_objects(memory, skip=6), author="cy")
    object_id, clusters = observed_often(memory, skip=3)
    curation.split(memory, object_id, clusters[-2:], author="cy")
    settle(memory)
    live = beliefs(memory)
    assert live[relabelled.id][0][0] == "teapot"
    request_rebuild(memory)
    settle(memory)
    assert beliefs(memory) == live


def test_exports_use_corrected_labels_say_so_and_skip_rejected_detections(memory):
    for skip in range(10, 100):  # a scene with two more classified clusters not corrected
        relabelled = a_classified_cluster(memory, skip=skip)
        scene = memory.get_scene(relabelled.scene_id)
        others = [c for c in scene.clusters if c.id != relabelled.id
                  and c.annotations_of(Classification) and verdict(c.annotations) is None]
        if len(others) >= 2:
            break
    rejected = others[0]
    made = curation.relabel(memory, relabelled.id, "mug", author="cy")
    curation.reject(memory, rejected.id, author="cy")
    query = ExportQuery(format="jsonl", label="classification", at=scene.timestamp)
    export = Export(memory, query)
    data = b"".join(export.zip_stream())
    archive = zipfile.ZipFile(io.BytesIO(data))
    manifest = json.loads(archive.read("manifest.json"))
    records = {r["cluster_id"]: r for r in map(json.loads,
                                               archive.read("provenance.jsonl").splitlines())}
    assert records[str(relabelled.id)]["label"] == "mug"
    assert records[str(relabelled.id)]["corrected"] is True
    assert records[str(relabelled.id)]["annotator"] == "human:cy"
    assert records[str(relabelled.id)]["annotation_id"] == str(made.id)
    assert str(rejected.id) not in records
    now = memory.get_scene(scene.id).clusters  # (earlier tests may have corrected some)
    assert manifest["skipped"]["rejected by a person"] == sum(
        isinstance(verdict(c.annotations), Rejection) for c in now)
    assert manifest["corrected"] == sum(isinstance(verdict(c.annotations), Relabel)
                                        for c in now) >= 1
    others = [r for r in records.values() if not r["corrected"]]
    assert others and all(r["annotator"] != "human:cy" for r in others)
    assert all(memory.get_cluster(ObjectId(r["cluster_id"])).annotations_of(Classification)
               for r in others)


def test_an_object_relabelled_in_other_letters_is_one_class_in_an_object_export(memory):
    """Relabelled "Teapot OF Grandma", the cluster's object is named "teapot of grandma"
    (names are normalised): exported by object, its clusters were two classes that differ
    in case only (two folders on a case-insensitive disk); now the object's name for all,
    the corrected one still saying who corrected it."""
    relabelled = a_classified_cluster(memory, skip=40)
    made = curation.relabel(memory, relabelled.id, "Teapot OF Grandma", author="di")
    settle(memory)
    object_id = memory.get_cluster(relabelled.id).object_id
    query = ExportQuery(format="jsonl", label="object", object=[object_id])
    archive = zipfile.ZipFile(io.BytesIO(b"".join(Export(memory, query).zip_stream())))
    records = [json.loads(line) for line in archive.read("provenance.jsonl").splitlines()]
    assert len(records) > 1
    assert {r["label"] for r in records} == {"teapot of grandma"}
    mine = next(r for r in records if r["cluster_id"] == str(relabelled.id))
    assert (mine["corrected"], mine["annotator"], mine["annotation_id"]) == (
        True, "human:di", str(made.id))


@pytest.mark.parametrize("call, message", [
    (lambda s, c: curation.relabel(s, c.id, "  ", author="ana"), "class_name"),
    (lambda s, c: curation.relabel(s, c.id, "mug", author=" "), "author"),
    (lambda s, c: curation.relabel(s, c.id, "x" * 201, author="ana"), "class_name"),
    (lambda s, c: curation.undo(s, c.id, ObjectId(), author="ana"), "no correction"),
])
def test_bad_corrections_are_refused_naming_why_and_write_nothing(memory, call, message):
    cluster = a_classified_cluster(memory, skip=12)
    with pytest.raises(curation.NotCorrectable, match=message):
        call(memory, cluster)
    assert memory.get_cluster(cluster.id).annotations == cluster.annotations


def test_a_correction_of_a_cluster_not_stored_is_not_found(memory):
    with pytest.raises(NotFound):
        curation.relabel(memory, ObjectId(), "mug", author="ana")
