"""MemoryStore and AsyncMemoryStore on the real embedded mongod."""

from __future__ import annotations

import asyncio
import itertools
import re

import bson
import numpy as np
import pytest
from bson import ObjectId
from gridfs import GridFSBucket
from pymongo import AsyncMongoClient

from percept_memory.converters import Unknown, decode, encode
from percept_memory.ingest import synthetic
from percept_memory.memory import documents as docs
from percept_memory.memory.async_store import AsyncMemoryStore
from percept_memory.memory.errors import DuplicateId, NotFound, SceneExists, TooLarge
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore
from percept_memory.memory.types import (
    Cluster,
    FeatureVector,
    Image,
    ImageROI,
    Product,
    Scene,
    Shape,
    Text,
)

from .conftest import ROBOSHERLOCK

_clock = itertools.count(1_522_249_987_296_654_516, 33_000_000)


def a_scene(kitchen_rgb, clusters: int = 6, seed: int = 0) -> Scene:
    scene = synthetic.scene(np.random.default_rng(seed), next(_clock), clusters, kitchen_rgb)
    scene.images["color"] = Image(data=kitchen_rgb, encoding="bgr8")
    return scene


def snapshot(store: MemoryStore) -> dict:
    return {name: store.db[name].count_documents({})
            for name in ("scenes", "clusters", "binaries", "fs.files", "fs.chunks")}


def binaries(value):
    if isinstance(value, bytes):
        yield value
    for item in value.values() if isinstance(value, dict) else \
            value if isinstance(value, list) else ():
        yield from binaries(item)


def test_a_stored_scene_reads_back_equal(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb)
    ids = store.put_scene(scene)
    assert ids.scene_id == scene.id and len(ids.cluster_ids) == 6
    assert all(len(a) == 20 for a in ids.annotation_ids)
    back = store.get_scene(ids.scene_id)
    assert back == scene
    assert back.clusters[0].scene_id == scene.id


def test_scene_documents_are_small_and_queryable(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb)
    store.put_scene(scene)
    doc = store.scenes.find_one({"_id": scene.id})
    assert doc["clusters"] == [c.id for c in scene.clusters]
    assert doc["summary"]["clusters"] == 6
    assert len(bson.encode(doc)) < 20_000  # the full image lives in GridFS
    cluster_doc = store.clusters.find_one({"_id": scene.clusters[0].id})
    search = cluster_doc["search"]
    assert search["time"] == scene.timestamp and search["robot"] == "pr2"
    assert search["region"] == scene.clusters[0].region
    assert search["position"] == list(scene.clusters[0].position)
    assert "pm.annotation.FeatureVector" in search["types"]
    assert scene.clusters[0].annotations_of(Shape)[0].shape in search["labels"]


def test_blobs_are_real_gridfs_files(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb, clusters=1)
    store.put_scene(scene)
    (blob_id,) = store.scenes.find_one({"_id": scene.id})["_blobs"]
    png = GridFSBucket(store.db).open_download_stream(blob_id).read()
    assert png.startswith(b"\x89PNG")
    assert store.get_blob(blob_id) == png


def test_crops_leave_the_cluster_documents_and_read_back(store, kitchen_rgb):
    """Queries scan cluster documents: a crop is a document of `binaries` they refer to,
    loaded with the cluster, and a read without pixels (a projection) fetches no blob."""
    scene = a_scene(kitchen_rgb, clusters=2, seed=5)
    store.put_scene(scene)
    doc = store.clusters.find_one({"_id": scene.clusters[0].id})
    (roi,) = [h for h in doc["hypotheses"] if h.get("crop")]
    crop_id = roi["crop"]["data"]["_blob"]
    assert store.binaries.count_documents({"_id": crop_id}) == 1
    assert max(map(len, binaries(doc))) <= store.gridfs_threshold  # no pixels
    assert crop_id in docs.blob_ids([doc])
    assert docs.blob_ids([store.clusters.find_one(
        {"_id": scene.clusters[0].id}, {"hypotheses.crop": 0})]) == []
    assert store.get_cluster(scene.clusters[0].id) == scene.clusters[0]
    before = snapshot(store)
    twin = scene.model_copy(deep=True)  # the same scene posted again
    assert not store.put_scene(twin).created
    assert snapshot(store) == before


def test_a_write_stores_each_blob_once(store, kitchen_rgb):
    """Clusters of a write, and of later writes, showing the same crop share one blob."""
    crop = Image(data=kitchen_rgb[:64, :64].copy(), encoding="bgr8")
    scenes = [Scene(timestamp=next(_clock), clusters=[
        Cluster(hypotheses=[ImageROI(box=(0, 0, 64, 64), crop=crop)])
        for _ in range(3)]) for _ in range(2)]
    before = snapshot(store)
    store.put_scenes(scenes[:1])
    store.put_scenes(scenes[1:])
    after = snapshot(store)
    assert after["binaries"] - before["binaries"] == 1
    assert store.get_scene(scenes[1].id) == scenes[1]


def test_arrays_over_16_mb_go_to_gridfs(store):
    big = np.random.default_rng(2).standard_normal(2_200_000)  # 17.6 MB
    scene = Scene(timestamp=next(_clock), clusters=[
        Cluster(annotations=[FeatureVector(name="dense", vector=big)])
    ])
    store.put_scene(scene)
    assert store.get_scene(scene.id) == scene


def test_a_write_that_fails_part_way_leaves_nothing(store, kitchen_rgb):
    first = a_scene(kitchen_rgb, clusters=2, seed=1)
    store.put_scene(first)
    before = snapshot(store)
    second = a_scene(kitchen_rgb, clusters=3, seed=2)
    second.images["extra"] = Image(data=np.random.default_rng(9).integers(
        0, 255, (480, 640, 3), dtype=np.uint8))  # a new blob, written before the clusters
    second.clusters[2].id = first.clusters[0].id  # the third cluster insert fails
    with pytest.raises(DuplicateId, match=str(first.clusters[0].id)):
        store.put_scene(second)
    assert snapshot(store) == before
    assert store.scenes.find_one({"_id": second.id}) is None


def test_a_document_too_large_leaves_nothing(store, kitchen_rgb):
    before = snapshot(store)
    huge = Scene(timestamp=next(_clock), clusters=[
        Cluster(annotations=[Text(text="fine")]),
        Cluster(annotations=[FeatureVector(name="x", vector=np.zeros(2_200_000))]),
    ])
    inline = MemoryStore(store.client, store.db.name, gridfs_threshold=64 * 1024 * 1024)
    with pytest.raises(TooLarge, match="PMEM_GRIDFS_THRESHOLD"):
        inline.put_scene(huge)
    assert snapshot(store) == before


def test_storing_the_same_scene_again_is_a_no_op(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb, clusters=2)
    first = store.put_scene(scene)
    assert first.created
    before = snapshot(store)
    again = store.put_scene(scene)
    assert (again.scene_id, again.cluster_ids, again.annotation_ids) == (
        first.scene_id, first.cluster_ids, first.annotation_ids)
    assert not again.created
    assert snapshot(store) == before


def test_a_scene_is_identified_by_robot_and_time(store):
    """The same scene again, as another object, is the scene stored: its stored ids come back
    and nothing is written (a retry), also once it has been consolidated and enriched; a
    different scene of the robot at that time is refused, not acknowledged and lost; another
    robot at that time is another scene."""
    t = next(_clock)

    def milk():
        return Scene(timestamp=t, robot="tiago", clusters=[Cluster(annotations=[
            Text(text="milk")])])
    scene = milk()
    stored = store.put_scene(scene)
    store.add_annotation(stored.cluster_ids[0], Text(text="lookup: milk 1 l"))  # enrichment
    store.clusters.update_one({"_id": stored.cluster_ids[0]}, {"$set": {"object_id": ObjectId()}})
    before = snapshot(store)
    twin = milk()
    repeated = store.put_scene(twin)
    assert twin.id is None and twin.clusters[0].id is None  # given no ids that were not stored
    assert not repeated.created
    assert repeated.scene_id == scene.id
    assert repeated.annotation_ids[0][:1] == stored.annotation_ids[0]
    assert snapshot(store) == before
    for other in (Scene(timestamp=scene.timestamp, robot="tiago", clusters=[Cluster()]),
                  Scene(timestamp=scene.timestamp, robot="tiago", clusters=[Cluster(
                      annotations=[Text(text="milk")]), Cluster()])):
        with pytest.raises(SceneExists, match="'tiago' has another scene stored at timestamp"):
            store.put_scenes([Scene(timestamp=next(_clock), robot="tiago"), other])
        assert snapshot(store) == before and other.id is None  # nothing of the batch written
    assert store.put_scene(Scene(timestamp=scene.timestamp, robot="pr2")).created


def test_two_different_scenes_at_one_robot_and_time_in_a_batch_are_refused(store):
    """The second was acknowledged and dropped (a batch wrote a key once, unchecked): now the
    batch is refused as a scene stored before would refuse it, whether the two came in one
    chunk or in two, and nothing of it is written or given ids."""
    t = next(_clock)

    def scene(text: str) -> Scene:
        return Scene(timestamp=t, robot="tiago", clusters=[Cluster(annotations=[
            Text(text=text)])])
    before = snapshot(store)
    for put in (lambda a, b: store.put_scenes([a, b]),
                lambda a, b: store.put_scene_chunks([[a], [b]])):
        first, other = scene("milk"), scene("oat milk")
        with pytest.raises(SceneExists, match="two different scenes at timestamp .* batch"):
            put(first, other)
        assert snapshot(store) == before
        assert first.id is None and other.id is None and first.clusters[0].id is None
    assert [r.created for r in store.put_scenes([scene("milk"), scene("milk")])] == [True, False]


def test_a_batch_is_one_write_and_skips_what_is_stored(store, kitchen_rgb):
    stored_before = a_scene(kitchen_rgb, clusters=1, seed=11)
    store.put_scene(stored_before)
    batch = [a_scene(kitchen_rgb, clusters=2, seed=12), stored_before,
             a_scene(kitchen_rgb, clusters=3, seed=13)]
    twin = batch[0].model_copy(deep=True)  # the same scene twice in one batch
    twin.id = None
    results = store.put_scenes([*batch, twin])
    assert [r.created for r in results] == [True, False, True, False]
    assert results[3].scene_id == results[0].scene_id == batch[0].id
    assert store.scenes.count_documents({"_id": {"$in": [s.id for s in batch]}}) == 3
    for scene in batch:
        assert store.get_scene(scene.id) == scene


def test_a_batch_that_fails_leaves_nothing(store, kitchen_rgb):
    taken = a_scene(kitchen_rgb, clusters=1, seed=21)
    store.put_scene(taken)
    before = snapshot(store)
    batch = [a_scene(kitchen_rgb, clusters=2, seed=22), a_scene(kitchen_rgb, clusters=2, seed=23)]
    batch[1].clusters[1].id = taken.clusters[0].id
    with pytest.raises(DuplicateId):
        store.put_scenes(batch)
    assert snapshot(store) == before
    # one new id given to clusters of two scenes of the write: none stored with it
    within = [a_scene(kitchen_rgb, clusters=1, seed=24), a_scene(kitchen_rgb, clusters=1, seed=25)]
    within[0].clusters[0].id = within[1].clusters[0].id = ObjectId()
    with pytest.raises(DuplicateId, match="another document, stored or earlier in this write"):
        store.put_scenes(within)
    assert snapshot(store) == before


def test_clusters_sharing_a_big_blob_each_read_back(store):
    shared = np.random.default_rng(8).random(40_000)  # 320 kB: a blob, stored once
    scene = Scene(timestamp=next(_clock), clusters=[
        Cluster(annotations=[FeatureVector(name="same", vector=shared)]) for _ in range(2)
    ])
    before = store.files.count_documents({})
    store.put_scene(scene)
    assert store.files.count_documents({}) == before + 1
    for cluster in scene.clusters:
        assert store.get_cluster(cluster.id) == cluster


def fresh_summary(store, scene_id) -> dict:
    """The summary the scene's document would have if it were written now."""
    (written,) = docs.scene_documents([store.get_scene(scene_id)], store.gridfs_threshold).scenes
    return bson.decode(written.raw)["summary"]


def test_appending_an_annotation_is_idempotent_and_updates_search(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb, clusters=1)
    store.put_scene(scene)
    cluster_id = scene.clusters[0].id
    lookup = Product(source="WebAnnotator", name="Pringles Paprika", brand="Pringles")
    annotation_id = store.add_annotation(cluster_id, lookup)
    store.add_annotation(cluster_id, lookup)  # a retried job
    stored = store.get_cluster(cluster_id)
    assert [a.id for a in stored.annotations].count(annotation_id) == 1
    assert stored.annotations[-1] == lookup
    assert "pringles paprika" in store.clusters.find_one({"_id": cluster_id})["search"]["labels"]
    store.add_annotation(cluster_id, Product(source="$summary.types", name="$labels"))  # data
    summary = store.scenes.find_one({"_id": scene.id})["summary"]  # grown in place, sorted
    assert {"WebAnnotator", "$summary.types"} <= set(summary["annotators"])
    assert {"pringles paprika", "$labels"} <= set(summary["labels"])
    assert summary == fresh_summary(store, scene.id)


def test_appending_to_a_missing_cluster_says_so(store):
    with pytest.raises(NotFound, match="no cluster"):
        store.add_annotation(ObjectId(), Text(text="x"))


def test_updating_an_annotation_replaces_it_in_place(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb, clusters=1)
    store.put_scene(scene)
    cluster = scene.clusters[0]
    shape = cluster.annotations_of(Shape)[0]
    store.update_annotation(cluster.id, shape.model_copy(update={"shape": "torus"}))
    stored = store.get_cluster(cluster.id)
    assert stored.annotations_of(Shape)[0].shape == "torus"
    assert stored.annotations_of(Shape)[0].id == shape.id
    assert len(stored.annotations) == len(cluster.annotations)
    with pytest.raises(NotFound, match="annotation"):
        store.update_annotation(cluster.id, Shape(id=ObjectId(), shape="cone"))
    assert store.get_cluster(cluster.id) == stored


def test_updating_a_cluster(store, kitchen_rgb):
    scene = a_scene(kitchen_rgb, clusters=1)
    store.put_scene(scene)
    cluster = scene.clusters[0]
    cluster.object_id = ObjectId()
    cluster.annotations = cluster.annotations[:3]
    store.update_cluster(cluster)
    assert store.get_cluster(cluster.id) == cluster
    summary = store.scenes.find_one({"_id": scene.id})["summary"]  # kept exact: types dropped
    assert summary["types"] == sorted({a.type_name for a in cluster.annotations})
    assert summary == fresh_summary(store, scene.id)


def test_robosherlock_annotations_we_do_not_know_survive_storage(store):
    """Real `rs.*` documents of types we have no class for are kept byte for byte."""
    path = ROBOSHERLOCK / "mongodump" / "PnP09ObjSymbolicGTFixed" / "persistent_objects.bson"
    with open(path, "rb") as dump:
        rs_object = next(bson.decode_file_iter(dump))
    rs_annotations = [a for a in rs_object["annotations"] if a["_type"] in (
        "rs.annotation.Geometry", "rs.annotation.SemanticColor", "rs.annotation.Features")]
    cluster = Cluster(annotations=[decode(a) for a in rs_annotations])
    assert all(isinstance(a, Unknown) for a in cluster.annotations)
    scene = Scene(timestamp=rs_object["lastSeen"], robot="pr2", clusters=[cluster])
    ids = store.put_scene(scene)
    assert ids.annotation_ids == [[a["_id"] for a in rs_annotations]]
    assert store.put_scene(scene).annotation_ids == ids.annotation_ids
    back = store.get_cluster(cluster.id)
    assert [bson.encode(encode(a)) for a in back.annotations] == [
        bson.encode(a) for a in rs_annotations
    ]


@pytest.mark.parametrize("size, home", [(3000, "binaries"), (512_000, "fs.files")])
def test_put_and_get_blob_by_content(store, size, home):
    data = (bytes(range(256)) * 2000)[:size]
    blob_id = store.put_blob(data)
    assert store.put_blob(data) == blob_id
    assert store.db[home].count_documents({"_id": blob_id}) == 1
    assert store.get_blob(blob_id) == data
    with pytest.raises(NotFound, match="blob"):
        store.get_blob("sha256:00")


def test_the_catalogue_describes_the_stored_types(store, kitchen_rgb):
    store.put_scene(a_scene(kitchen_rgb, clusters=1))
    catalogue = {entry["_id"]: entry for entry in store.catalogue()}
    assert catalogue["pm.annotation.Classification"]["fields"]["class_name"] == {
        "type": "str", "required": True}
    assert catalogue["pm.annotation.Classification"]["aliases"] == [
        "rs.annotation.Classification"]
    assert catalogue["pm.annotation.Classification"]["kind"] == "Annotation"
    assert catalogue["pm.raw.Image"]["known"] is True


def test_counts_per_collection_and_type(store):
    counts = store.counts()
    clusters = store.clusters.count_documents({})
    assert counts["collections"]["clusters"] == clusters
    text_annotations = sum(
        1 for doc in store.clusters.find({}, {"annotations._type": 1})
        for a in doc["annotations"] if a["_type"] == "pm.annotation.Text"
    )
    assert counts["types"]["pm.annotation.Text"] == text_annotations > 0


@pytest.mark.parametrize("query", [
    {"scene_id": ObjectId()},
    {"search.terms": "cereal"},
    {"search.region": "counter_top_sink", "search.time": {"$gt": 0}},
    {"annotations": {"$elemMatch": {"_type": "pm.annotation.Logo", "brand": "Ja!"}}},
    {"object_id": ObjectId()},
])
def test_cluster_query_paths_use_an_index(store, query):
    store.add_field_index("brand")  # what people ask about gets one
    plan = store.clusters.find(query).explain()["queryPlanner"]["winningPlan"]
    assert "IXSCAN" in str(plan), plan


def test_prepare_drops_the_indexes_no_query_uses_any_more(store):
    store.clusters.create_index("search.labels", name="labels")  # as an older version did
    store.clusters.create_index([("search.fields.k", 1), ("search.fields.v", 1)], name="fields")
    store.add_field_index("brand")  # a user's: kept
    store.prepare()
    present = set(store.clusters.index_information())
    assert not {"labels", "fields"} & present
    assert {"field:brand", "terms_newest", "morton_xyz"} <= present


# --- the async store -------------------------------------------------------------------


def run_async(mongo_uri: str, db_name: str, work):
    async def main():
        client = AsyncMongoClient(mongo_uri, **CLIENT_OPTIONS)
        memory = AsyncMemoryStore(client, db_name, gridfs_threshold=128 * 1024)
        await memory.prepare()
        try:
            return await work(memory)
        finally:
            await memory.close()

    return asyncio.run(main())


def test_async_store_round_trip_and_append(mongo_uri, db_name, kitchen_rgb):
    scene = a_scene(kitchen_rgb, clusters=2, seed=5)

    async def work(memory: AsyncMemoryStore):
        ids = await memory.put_scene(scene)
        again = await memory.put_scene(scene)
        assert (again.scene_id, again.cluster_ids, again.created) == (
            ids.scene_id, ids.cluster_ids, False)
        back = await memory.get_scene(ids.scene_id)
        await memory.add_annotation(ids.cluster_ids[0], Text(text="Hohes C", source="LateOCR"))
        summary = (await memory.scenes.find_one({"_id": ids.scene_id}))["summary"]
        return back, await memory.get_cluster(ids.cluster_ids[0]), await memory.counts(), summary

    back, cluster, counts, summary = run_async(mongo_uri, db_name, work)
    assert back == scene
    assert "LateOCR" in summary["annotators"]  # the scene log finds it by its new annotator
    assert cluster.annotations[-1].text == "Hohes C"
    assert counts["collections"]["scenes"] >= 1


def test_async_writes_go_on_past_a_connection_handshaken_while_mongod_was_starting(
        mongo_uri, db_name, kitchen_rgb):
    """As the sync store's (test_pipeline.py): an enrichment job's append and the web app's
    ingest are not refused for ever by a connection opened before mongod was a primary."""
    scene = a_scene(kitchen_rgb, clusters=1, seed=6)

    async def work(memory: AsyncMemoryStore):
        await memory.scenes.find_one({})
        for server in memory.client._topology._servers.values():
            for connection in server.pool.conns:
                connection.supports_sessions = False  # what its handshake said while starting
        ids = await memory.put_scene(scene)
        await memory.add_annotation(ids.cluster_ids[0], Text(text="Hohes C", source="LateOCR"))
        return await memory.get_cluster(ids.cluster_ids[0])

    assert run_async(mongo_uri, db_name, work).annotations[-1].text == "Hohes C"


def test_a_wrong_argument_is_a_type_error_naming_it_and_writes_nothing(store, mongo_uri,
                                                                       db_name):
    """A dict where a Scene belongs, a Scene appended as an annotation, a str id: they were
    AttributeErrors from deep inside, a Scene stored inside a cluster's annotations, and
    "no cluster <the id of one that exists>"."""
    ids = store.put_scene(Scene(timestamp=next(_clock), robot="args", clusters=[Cluster()]))
    cluster = ids.cluster_ids[0]
    before = snapshot(store)
    for call, words in [
            (lambda: store.put_scene({"timestamp": 1}), "scenes: expected Scene, got dict"),
            (lambda: store.put_scene(None), "scenes: expected Scene, got NoneType"),
            (lambda: store.add_annotation(cluster, Scene(timestamp=1)),
             "annotations: expected Annotation, got Scene"),
            (lambda: store.add_annotation(cluster, Cluster()),
             "annotations: expected Annotation, got Cluster"),
            (lambda: store.add_annotation(cluster, {"_type": "pm.annotation.Text"}),
             "annotations: expected Annotation, got dict"),
            (lambda: store.update_annotation(cluster, Cluster()),
             "annotation: expected Annotation, got Cluster"),
            (lambda: store.update_cluster("x"), "cluster: expected Cluster, got str"),
            (lambda: store.get_scene("junk"), "scene_id: expected an ObjectId or its 24"),
            (lambda: store.put_blob("hello"), "data: expected bytes or bytearray or memoryview")]:
        with pytest.raises(TypeError, match=re.escape(words)):
            call()
    assert snapshot(store) == before
    added = store.add_annotation(str(cluster), Text(text="x"))  # its hex digits: the cluster
    assert store.get_cluster(str(cluster)).annotations[-1].id == added

    async def appended(memory: AsyncMemoryStore):
        with pytest.raises(TypeError, match="expected Annotation, got Scene"):
            await memory.add_annotation(cluster, Scene(timestamp=1))
        return await memory.add_annotation(str(cluster), Text(text="y"))

    assert run_async(mongo_uri, db_name, appended) in [
        a.id for a in store.get_cluster(cluster).annotations]


def test_concurrent_appends_to_one_cluster_all_land(mongo_uri, db_name, store):
    """Write conflicts between transactions are retried: none of the appends is lost."""
    scene = Scene(timestamp=next(_clock), clusters=[Cluster()])
    store.put_scene(scene)
    cluster_id = scene.clusters[0].id

    async def work(memory: AsyncMemoryStore):
        texts = [Text(text=f"lookup {i}") for i in range(12)]
        await asyncio.gather(*(memory.add_annotation(cluster_id, t) for t in texts))
        await asyncio.gather(*(memory.add_annotation(cluster_id, t) for t in texts))
        return await memory.get_cluster(cluster_id)

    cluster = run_async(mongo_uri, db_name, work)
    assert sorted(a.text for a in cluster.annotations) == sorted(f"lookup {i}" for i in range(12))


def test_a_batch_too_big_for_one_transaction_is_written_in_parts(store):
    """150 scenes of 1 MB of incompressible pixels outgrow what the test mongod's 256 MB cache
    holds in one transaction (TransactionTooLargeForCache): the batch is written in smaller
    transactions, every scene whole, with the ids it was given."""
    rng = np.random.default_rng(5)
    scenes = [Scene(timestamp=7_000_000_000_000_000_000 + i, robot="big-batch", images={
        "rgb": Image(data=rng.integers(0, 255, (600, 600, 3), dtype=np.uint8), encoding="bgr8")})
        for i in range(150)]
    ids = store.put_scenes(scenes)
    assert [i.scene_id for i in ids] == [s.id for s in scenes]
    assert store.scenes.count_documents({"robot": "big-batch"}) == 150
    again = store.get_scene(scenes[77].id)
    assert np.array_equal(again.images["rgb"].data, scenes[77].images["rgb"].data)


def test_reindex_brings_data_of_an_older_version_up_to_date(store):
    """Derived fields missing or stale (as stored by an older version): reindex recomputes
    each cluster's search keys and each scene's summary exactly as a fresh store writes them."""
    rng = np.random.default_rng(11)
    scene = synthetic.scene(rng, 8_000_000_000_000_000_000, clusters=3)
    store.put_scene(scene)
    ids = [c.id for c in scene.clusters]
    fresh_clusters = {d["_id"]: d["search"] for d in store.clusters.find({"_id": {"$in": ids}})}
    fresh_scene = store.scenes.find_one({"_id": scene.id})["summary"]
    stale = {"$unset": {"search.x": "", "search.terms": ""},  # and an older version's key:
             "$set": {"search.fields": [{"k": "pm.annotation.Shape:shape", "v": "box"}]}}
    store.clusters.update_many({"_id": {"$in": ids}}, stale)
    store.scenes.update_one({"_id": scene.id}, {"$unset": {"summary": ""}})

    assert store.reindex() == store.clusters.count_documents({})
    assert {d["_id"]: d["search"] for d in store.clusters.find({"_id": {"$in": ids}})} == \
        fresh_clusters
    assert store.scenes.find_one({"_id": scene.id})["summary"] == fresh_scene
