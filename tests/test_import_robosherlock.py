"""The RoboSherlock importer on the real dumps in shared/data, stored in the real mongod.

Expected values are read from the BSON files directly (bson.decode_file_iter), not through the
importer, so the importer is checked against the data and not against itself.
"""

from __future__ import annotations

import copy
import logging
import shutil
from collections import Counter
from pathlib import Path

import bson
import numpy as np
import pytest
from pymongo import MongoClient

from percept_memory.converters import Unknown
from percept_memory.ingest.errors import SourceError
from percept_memory.ingest.robosherlock import (
    RoboSherlockFormatError,
    read_collections,
    read_database,
    read_dump,
)
from percept_memory.ingest.scene_log import read_scene_log, write_scene_log
from percept_memory.ingest.service import IngestService
from percept_memory.memory.documents import assign_ids
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import (
    Classification,
    FeatureVector,
    GroundTruth,
    ImageROI,
    PointCluster,
    SemanticColor,
)

from .conftest import ROBOSHERLOCK

IJRR = ROBOSHERLOCK / "mongodump" / "IJRRScenes"
PNP = ROBOSHERLOCK / "mongodump" / "PnP09ObjSymbolicGTFixed"

# What each RoboSherlock type found in PnP09's persistent objects is stored as.
STORED_AS = {
    "rs.annotation.GroundTruth": "pm.annotation.GroundTruth",
    "rs.annotation.Detection": "pm.annotation.Detection",
    "rs.annotation.Shape": "pm.annotation.Shape",
    "rs.annotation.SemanticColor": "pm.annotation.SemanticColor",
    "rs.annotation.ColorHistogram": "pm.annotation.ColorHistogram",
    "rs.annotation.Geometry": "pm.annotation.Geometry",
    "rs.annotation.SemanticSize": "pm.annotation.Geometry",
    "rs.annotation.PoseAnnotation": "pm.annotation.Location",
    "rs.annotation.Features": "pm.annotation.FeatureVector",
    "rs.pcl.PclFeature": "pm.annotation.FeatureVector",
    "rs.annotation.Segment": "rs.annotation.Segment",  # no type of ours: kept whole
}


def is_lfs_pointer(path: Path) -> bool:
    return path.read_bytes().startswith(b"version https://git-lfs")


def raw(folder: Path, collection: str) -> list[dict]:
    """A collection of a dump as the BSON file holds it."""
    with (folder / f"{collection}.bson").open("rb") as file:
        return list(bson.decode_file_iter(file))


def raw_collections(folder: Path) -> dict[str, list[dict]]:
    return {
        path.stem: raw(folder, path.stem)
        for path in folder.glob("*.bson")
        if not path.name.startswith("system.") and not is_lfs_pointer(path)
    }


def kept_object(cluster) -> dict:
    """The RoboSherlock rs.scene.Object a cluster was imported from, as the importer kept it."""
    (kept,) = [a for a in cluster.annotations
               if isinstance(a, Unknown) and a.type_name == "rs.scene.Object"]
    return kept.fields


def ingest(store, scenes) -> list:
    """The ids of the scenes, stored through the ingest service as every importer is."""
    items = ((f"frame at {scene.timestamp}", scene) for scene in scenes)
    return [ingested.ids for ingested in IngestService(store).ingest_stream(items)]


def snapshot(store) -> dict:
    return {name: store.db[name].count_documents({})
            for name in ("scenes", "clusters", "fs.files", "fs.chunks")}


@pytest.fixture(scope="module")
def pnp(store):
    """PnP09 imported and stored once for the module: (scenes, their ids)."""
    scenes = list(read_dump(PNP))
    return scenes, ingest(store, scenes)


@pytest.fixture(scope="module")
def objects(pnp) -> list[tuple[dict, object]]:
    """(RoboSherlock's persistent object, the cluster imported from it), for the 9 objects."""
    raw_objects = {doc["_id"]: doc for doc in raw(PNP, "persistent_objects")}
    clusters = [cluster for scene in pnp[0] for cluster in scene.clusters]
    return [(raw_objects[kept_object(c)["_id"]], c) for c in clusters]


# --- IJRRScenes: frames, camera pose and intrinsics -----------------------------------------


def test_ijrr_frames_are_stored_with_the_camera_pose_and_intrinsics(store):
    cas, scene_docs = raw(IJRR, "cas"), {d["_id"]: d for d in raw(IJRR, "scene")}
    (camera_info,) = raw(IJRR, "camera_info")
    scenes = list(read_dump(IJRR, robot="pr2"))
    before = snapshot(store)
    ids = ingest(store, scenes)

    assert len(cas) == 11 and len(scenes) == len(cas) and all(i.created for i in ids)
    assert snapshot(store)["scenes"] == before["scenes"] + len(cas)
    assert [s.timestamp for s in scenes] == sorted(frame["_timestamp"] for frame in cas)
    for scene, frame, scene_ids in zip(scenes, sorted(cas, key=lambda f: f["_timestamp"]), ids,
                                       strict=True):
        viewpoint = scene_docs[frame["scene"]]["viewPoint"]
        pose = scene.camera_pose
        matrix = pose.matrix()
        np.testing.assert_allclose(matrix[:3, :3], np.reshape(viewpoint["rotation"], (3, 3)),
                                   rtol=0, atol=1e-9)
        assert pose.translation == tuple(viewpoint["translation"])
        assert (pose.frame, pose.child_frame, pose.stamp) == (
            viewpoint["frame"], viewpoint["childFrame"], viewpoint["timestamp"])
        assert scene.frame == "map"
        assert scene.camera.k == tuple(camera_info["k"])
        assert (scene.camera.width, scene.camera.height) == (640, 480)
        assert scene.camera.frame == camera_info["header"]["frame_id"]
        assert store.get_scene(scene_ids.scene_id) == scene


def test_a_quaternion_rotation_gives_the_same_pose_as_the_matrix():
    collections = raw_collections(IJRR)
    from_matrix = list(read_collections(collections))
    with_quaternions = copy.deepcopy(collections)
    by_time = {s.timestamp: s for s in from_matrix}
    for doc in with_quaternions["scene"]:
        doc["viewPoint"]["rotation"] = list(by_time[doc["timestamp"]].camera_pose.rotation)
    from_quaternion = list(read_collections(with_quaternions))
    for a, b in zip(from_quaternion, from_matrix, strict=True):
        np.testing.assert_allclose(a.camera_pose.matrix(), b.camera_pose.matrix(), atol=1e-12)
        assert a.camera_pose.child_frame == b.camera_pose.child_frame


# --- PnP09: persistent objects and their annotations -----------------------------------------


def test_pnp09_has_35_frames_and_each_object_in_the_frame_it_was_last_seen(pnp):
    scenes, ids = pnp
    cas, raw_objects = raw(PNP, "cas"), raw(PNP, "persistent_objects")
    assert len(cas) == len(scenes) == 35 and all(i.created for i in ids)
    assert len(raw_objects) == 9
    assert Counter(s.timestamp for s in scenes for _ in s.clusters) == Counter(
        o["lastSeen"] for o in raw_objects)
    assert {s.camera.k for s in scenes} == {tuple(raw(PNP, "camera_info")[0]["k"])}


def test_pnp09_annotation_counts_per_type_equal_the_dump(store, pnp):
    raw_objects = raw(PNP, "persistent_objects")
    in_dump = Counter(a["_type"] for o in raw_objects for a in o["annotations"])
    assert in_dump == {
        "rs.annotation.Features": 15, "rs.annotation.Shape": 15,
        "rs.annotation.PoseAnnotation": 10, "rs.annotation.ColorHistogram": 9,
        "rs.annotation.Geometry": 9, "rs.annotation.SemanticSize": 9,
        "rs.annotation.SemanticColor": 9, "rs.pcl.PclFeature": 9, "rs.annotation.Detection": 9,
        "rs.annotation.GroundTruth": 9, "rs.annotation.Segment": 6,
    }
    expected = Counter()
    for rs_type, count in in_dump.items():
        expected[STORED_AS[rs_type]] += count
    expected["rs.scene.Object"] = len(raw_objects)
    expected["pm.hypothesis.ImageROI"] = sum(
        bool(o["rois"][key]) for o in raw_objects for key in ("roi", "roi_hires"))
    expected["pm.hypothesis.PointCluster"] = sum(bool(o["points"]) for o in raw_objects)
    assert store.counts()["types"] == dict(expected)


def test_pnp09_feature_vectors_are_the_raw_little_endian_floats(objects):
    for doc, cluster in objects:
        vectors = {v.name: v for v in cluster.annotations_of(FeatureVector)}
        for annotation in doc["annotations"]:
            if annotation["_type"] == "rs.pcl.PclFeature":
                vfh = vectors[annotation["feat_type"]]
                assert annotation["feat_type"] == "VFH" and vfh.vector.shape == (308,)
                assert np.array_equal(vfh.vector, np.frombuffer(annotation["feature"], "<f4"))
            if annotation["_type"] == "rs.annotation.Features":
                mat = annotation["descriptors"]
                vector = vectors[annotation["source"]].vector
                assert vector.shape == (mat["rows"], mat["cols"]) and vector.dtype == np.float32
                assert vector.tobytes() == mat["data"]
        assert vectors["Caffe"].vector.shape == (1, 4096)


def test_pnp09_masks_boxes_and_point_indices_are_the_raw_data(objects):
    for doc, cluster in objects:
        rois = {roi.image: roi for roi in cluster.hypotheses if isinstance(roi, ImageROI)}
        for image, roi_key, mask_key in (("color", "roi", "mask"),
                                         ("color_hd", "roi_hires", "mask_hires")):
            rect, mask = doc["rois"][roi_key], doc["rois"][mask_key]
            roi = rois[image]
            assert roi.box == (rect["pos"]["x"], rect["pos"]["y"],
                               rect["size"]["width"], rect["size"]["height"])
            assert mask["mat_type"] == 0 and roi.mask.encoding == "mono8"
            assert roi.mask.data.shape == (mask["rows"], mask["cols"])
            assert roi.mask.data.tobytes() == mask["data"]
        (points,) = [h for h in cluster.hypotheses if isinstance(h, PointCluster)]
        raw_indices = doc["points"]["indices"]["indices"]
        assert np.array_equal(points.indices, np.frombuffer(raw_indices, "<i4"))


def test_pnp09_ground_truth_colours_and_sources(objects):
    for doc, cluster in objects:
        by_type = {}
        for annotation in doc["annotations"]:
            by_type.setdefault(annotation["_type"], []).append(annotation)
        (truth,) = by_type["rs.annotation.GroundTruth"]
        assert [g.class_name for g in cluster.annotations_of(GroundTruth)] == [
            truth["classificationGT"]["classname"]]
        (colour,) = by_type["rs.annotation.SemanticColor"]
        (ratios,) = cluster.annotations_of(SemanticColor)
        assert ratios.ratios == dict(zip(colour["color"], colour["ratio"], strict=True))
        mapped = [a for a in cluster.annotations if not isinstance(a, Unknown)]
        assert Counter((a.id, a.source) for a in mapped) == Counter(
            (a["_id"], a["source"]) for a in doc["annotations"]
            if a["_type"] != "rs.annotation.Segment")
    imported = Counter(g.class_name for _, c in objects for g in c.annotations_of(GroundTruth))
    assert imported == Counter(a["classificationGT"]["classname"]
                               for o in raw(PNP, "persistent_objects") for a in o["annotations"]
                               if a["_type"] == "rs.annotation.GroundTruth")
    assert imported.total() == 9


def test_an_imported_object_reads_back_equal(store, objects):
    _, cluster = objects[0]
    assert store.get_cluster(cluster.id) == cluster


def test_unknown_rs_types_survive_storage_byte_for_byte(store, objects):
    kept = 0
    for doc, cluster in objects:
        stored = store.clusters.find_one({"_id": cluster.id})
        stored_by_id = {a["_id"]: a for a in stored["annotations"]}
        for segment in (a for a in doc["annotations"] if a["_type"] == "rs.annotation.Segment"):
            assert bson.encode(stored_by_id[segment["_id"]]) == bson.encode(segment)
            kept += 1
        object_header = {k: v for k, v in doc.items() if k not in ("annotations", "rois", "points")}
        assert bson.encode(stored_by_id[doc["_id"]]) == bson.encode(object_header)
    assert kept == 6


@pytest.fixture
def another_store(store):
    """A store on a database of its own (the module's holds the dumps' ids already)."""
    memory = MemoryStore(store.client, f"{store.db.name}_log",
                         gridfs_threshold=store.gridfs_threshold)
    memory.prepare()
    yield memory
    store.client.drop_database(memory.db.name)


def test_the_dumps_written_as_a_scene_log_import_back_equal(another_store, tmp_path):
    """RoboSherlock's data handed on in the interchange format (write_scene_log): the ids,
    bytes and 64-bit integers of the documents kept whole travel as Extended JSON and come
    back as those values, and every pose to its last digit."""
    scenes = [*read_dump(PNP), *read_dump(IJRR)]
    for scene in scenes:
        assign_ids(scene)
    assert write_scene_log(scenes, tmp_path) == 46
    assert '{"$oid": ' in (tmp_path / "scenes.jsonl").read_text()
    landed = list(IngestService(another_store).ingest_stream(read_scene_log(tmp_path),
                                                             {"folder": tmp_path}))
    for scene, item in zip(scenes, landed, strict=True):
        assert item.ids.created and another_store.get_scene(item.ids.scene_id) == scene


def test_content_our_types_cannot_hold_keeps_the_document_whole():
    collections = raw_collections(PNP)
    first = min(collections["persistent_objects"], key=lambda o: str(o["_id"]))
    (truth,) = [a for a in first["annotations"] if a["_type"] == "rs.annotation.GroundTruth"]
    plain = copy.deepcopy(truth["classificationGT"])
    with_model = {**copy.deepcopy(plain), "_id": bson.ObjectId(), "model": "svm_rbf_every5th"}
    first["annotations"] += [plain, with_model]

    cluster = next(c for s in read_collections(collections) for c in s.clusters
                   if kept_object(c)["_id"] == first["_id"])
    (classification,) = cluster.annotations_of(Classification)
    assert (classification.id, classification.class_name, classification.classifier) == (
        plain["_id"], plain["classname"], "GroundTruth")
    (kept,) = [a for a in cluster.annotations if isinstance(a, Unknown)
               and a.type_name == "rs.annotation.Classification"]
    assert kept.fields == with_model


def test_importing_twice_creates_nothing(store, pnp):
    before = snapshot(store)
    again = ingest(store, read_dump(PNP))
    assert len(again) == 35 and not any(ids.created for ids in again)
    assert [ids.scene_id for ids in again] == [ids.scene_id for ids in pnp[1]]
    assert snapshot(store) == before


def test_lfs_pointer_files_are_skipped_with_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="percept_memory.ingest.robosherlock"):
        scenes = list(read_dump(PNP))
    assert len(scenes) == 35 and not any(s.images for s in scenes)
    warned = " ".join(r.getMessage() for r in caplog.records)
    for name in ("color_image_hd.bson", "depth_image_hd.bson"):
        assert is_lfs_pointer(PNP / name) and name in warned
    assert "git-lfs pointer" in warned


# --- malformed input ---------------------------------------------------------------------------


def test_a_malformed_document_names_collection_id_and_field():
    collections = raw_collections(PNP)
    bad = collections["persistent_objects"][3]
    bad["rois"]["mask"]["data"] = bad["rois"]["mask"]["data"][:-1]
    with pytest.raises(RoboSherlockFormatError) as error:
        list(read_collections(collections))
    assert (error.value.collection, error.value.doc_id, error.value.field) == (
        "persistent_objects", bad["_id"], "rois.mask.data")
    assert f"persistent_objects document {bad['_id']}" in str(error.value)

    collections = raw_collections(IJRR)
    del collections["cas"][2]["_timestamp"]
    with pytest.raises(RoboSherlockFormatError, match=r"cas document \w+: field _timestamp"):
        list(read_collections(collections))

    collections = raw_collections(IJRR)
    collections["scene"][0]["viewPoint"]["rotation"] = [1.0, 2.0, 3.0]
    with pytest.raises(RoboSherlockFormatError, match="field viewPoint.rotation: 3 numbers"):
        list(read_collections(collections))


def test_a_folder_that_is_no_dump_is_refused(tmp_path):
    with pytest.raises(SourceError, match="no cas.bson"):
        read_dump(tmp_path)


# --- a live RoboSherlock database ----------------------------------------------------------------


@pytest.fixture
def restored_pnp(mongo_uri: str, db_name: str):
    """PnP09 restored into a database of the test mongod, as mongorestore would."""
    name = f"{db_name}_rs"
    with MongoClient(mongo_uri) as client:
        for collection, docs in raw_collections(PNP).items():
            if docs:
                client[name][collection].insert_many(docs)
        yield name
        client.drop_database(name)


def test_read_database_gives_the_same_scenes_as_the_dump(mongo_uri, restored_pnp):
    from_database = list(read_database(mongo_uri, restored_pnp, map_name="pnp09"))
    assert len(from_database) == 35 and {s.map for s in from_database} == {"pnp09"}
    assert from_database == list(read_dump(PNP, map_name="pnp09"))
    assert {s.map for s in read_dump(PNP)} == {f"robosherlock/{PNP.name}"}


def test_a_truncated_dump_names_the_file(tmp_path):
    dump = tmp_path / "IJRRScenes"
    shutil.copytree(ROBOSHERLOCK / "mongodump" / "IJRRScenes", dump)
    scene_file = dump / "scene.bson"
    scene_file.chmod(0o644)
    scene_file.write_bytes(scene_file.read_bytes()[:-100])  # cut inside the last document
    with pytest.raises(SourceError, match=r"scene.bson is not a mongodump BSON file"):
        list(read_dump(dump))
