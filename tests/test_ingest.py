"""The ingest service, the interchange format v1 and scene-log folders, on the real mongod."""

from __future__ import annotations

import base64
import json
import logging
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from bson import Int64, ObjectId
from pymongo.errors import OperationFailure
from pymongo.synchronous.client_session import ClientSession

from percept_memory.ingest import synthetic
from percept_memory.ingest.scene_log import read_scene_log, write_scene_log
from percept_memory.ingest.service import CHUNK, IngestError, IngestService
from percept_memory.memory.documents import assign_ids
from percept_memory.memory.types import FeatureVector, Image, Scene

from .test_store import snapshot

STAMP = 1_600_000_000_000_000_000


def valid_scene(seed: int = 0, timestamp: int = STAMP, image=None) -> dict:
    """A realistic scene in its JSON interchange form."""
    scene = synthetic.scene(np.random.default_rng(seed), timestamp, 2, image)
    return json.loads(scene.model_dump_json(by_alias=True))


def at(data: dict, path: str):
    """The container and key a dotted path names, e.g. clusters.0.annotations.1.confidence."""
    *parents, last = path.split(".")
    for part in parents:
        data = data[int(part)] if isinstance(data, list) else data[part]
    return data, int(last) if isinstance(data, list) else last


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


A = "clusters.0.annotations"
LOCATION, CLASSIFICATION, VFH = f"{A}.0", f"{A}.1", f"{A}.7"
ROI = "clusters.0.hypotheses.0"
# (name, path, new value or DELETE, the path the error must name, words the message must hold)
DELETE = object()
MALFORMED = [
    ("missing timestamp", "timestamp", DELETE, "timestamp", "required"),
    ("timestamp as text", "timestamp", "yesterday", "timestamp", "integer"),
    ("timestamp as digits in a string", "timestamp", "1500000000000000000", "timestamp",
     "not a string"),
    ("timestamp as a float", "timestamp", 1.8e18, "timestamp", "lose the last digits"),
    ("negative timestamp", "timestamp", -5, "timestamp", "greater than or equal"),
    ("timestamp past int64", "timestamp", 2**64, "timestamp", "less than"),
    ("robot as a number", "robot", 7, "robot", "string"),
    ("unknown scene field", "colour", "red", "colour", "extra"),
    ("unknown annotation field", f"{CLASSIFICATION}.colour", "red", f"{CLASSIFICATION}.colour",
     "extra"),
    ("annotations not a list", f"{A}", {"a": 1}, A, "list"),
    ("annotation without _type", f"{CLASSIFICATION}._type", DELETE, CLASSIFICATION,
     "not a kind of Annotation"),
    ("misspelt _type", f"{CLASSIFICATION}._type", "pm.annotation.Clasification",
     CLASSIFICATION, "did you mean 'pm.annotation.Classification'"),
    ("a region of a MiB (its name filled every page and, 17 of them, the scene log's "
     "lists past MongoDB's 16 MB)", f"{LOCATION}.region", "r" * 2**20, f"{LOCATION}.region",
     "at most 200 characters"),
    ("a newline in a class name (a fake row in the CLI's tables)",
     f"{CLASSIFICATION}.class_name", "mug\n6b0c  undo  admin", f"{CLASSIFICATION}.class_name",
     "a name holds no control characters: '\\n' at 3"),
    ("an escape sequence in an annotator's name", f"{CLASSIFICATION}.source",
     "svm\x1b]52;c;ZWNobyBwd25lZAo=\x07", f"{CLASSIFICATION}.source", "control characters"),
    ("a right-to-left override in the robot's name", "robot", "pr2\u202egpj.exe", "robot",
     "control characters"),
    ("a box's image named by a MiB", f"{ROI}.image", "i" * 2**20, f"{ROI}.image",
     "at most 200 characters"),
    ("an escape in a class of a classifier's confidences",
     f"{CLASSIFICATION}.confidences", {"cup\x1b[2J": 0.5},
     f"{CLASSIFICATION}.confidences.cup\x1b[2J.[key]", "control characters"),
    ("a crop of three channels said to be mono8 (stored as said, misleading every reader)",
     f"{ROI}.crop.encoding", "mono8", f"{ROI}.crop",
     "encoding 'mono8' is 1 channel(s) of uint8, but the pixels are 3 channel(s) of uint8"),
    ("an encoding that is none", f"{ROI}.crop.encoding", "bogus99", f"{ROI}.crop",
     "encoding 'bogus99' is not an image encoding: one of ROS'"),
    ("our namespace in capitals (kept as another program's type)", f"{CLASSIFICATION}._type",
     "PM.annotation.Classification", CLASSIFICATION,
     "did you mean 'pm.annotation.Classification'"),
    ("a type's short name (its label was lost as an unknown type's)",
     f"{CLASSIFICATION}._type", "Classification", CLASSIFICATION,
     "named in full, with their namespace, such as 'lab.annotation.Weight'; did you mean "
     "'pm.annotation.Classification'"),
    ("hypothesis among annotations", f"{CLASSIFICATION}._type", "pm.hypothesis.ImageROI",
     CLASSIFICATION, "not a kind of Annotation"),
    ("_type not text", f"{CLASSIFICATION}._type", 12, CLASSIFICATION, "not a kind"),
    ("NaN coordinate", f"{LOCATION}.position.0", float("nan"), f"{LOCATION}.position.0",
     "finite"),
    ("infinite coordinate", f"{LOCATION}.position.2", float("inf"), f"{LOCATION}.position.2",
     "finite"),
    ("two coordinates", f"{LOCATION}.position", [1.0, 2.0], f"{LOCATION}.position.2",
     "required"),
    ("coordinate as text", f"{LOCATION}.position.1", "left", f"{LOCATION}.position.1",
     "number"),
    ("confidence above 1", f"{CLASSIFICATION}.confidence", 1.5,
     f"{CLASSIFICATION}.confidence", "less than or equal to 1"),
    ("NaN confidence", f"{CLASSIFICATION}.confidence", float("nan"),
     f"{CLASSIFICATION}.confidence", "finite number"),
    ("negative confidence", f"{CLASSIFICATION}.confidence", -0.1,
     f"{CLASSIFICATION}.confidence", "greater than or equal to 0"),
    ("negative box", f"{ROI}.box.0", -3, f"{ROI}.box.0", "greater than or equal to 0"),
    ("zero quaternion", "camera_pose.rotation", [0, 0, 0, 0], "camera_pose.rotation",
     "length 1"),
    ("pHash not hex", f"{ROI}.phash", "not-a-hash-at-all", f"{ROI}.phash", "pattern"),
    ("bad base64", f"{VFH}.vector.base64", "@@@not base64@@@", f"{VFH}.vector",
     "not valid base64"),
    ("bytes do not fit the shape", f"{VFH}.vector.shape", [309], f"{VFH}.vector", "needs 1236"),
    ("huge array", f"{VFH}.vector.shape", [100_000, 100_000, 100], f"{VFH}.vector",
     "larger than"),
    ("array of words", f"{VFH}.vector", ["a", "b"], f"{VFH}.vector", "numbers only"),
    ("ragged array", f"{VFH}.vector", [[1, 2], [3]], f"{VFH}.vector", "inhomogeneous"),
    ("unknown dtype", f"{VFH}.vector.dtype", "float-ish", f"{VFH}.vector", "unknown dtype"),
    ("dtype as an object", f"{VFH}.vector.dtype", {"0,": None}, f"{VFH}.vector",
     "unknown dtype"),
    ("structured dtype of a field without a type", f"{VFH}.vector.dtype", [["x"]],
     f"{VFH}.vector", "unknown dtype"),
    ("structured dtype of huge fields", f"{VFH}.vector.dtype", [["x", "<f8", [2**20, 2**20]]],
     f"{VFH}.vector", "unknown dtype"),
    ("image that does not decode", f"{ROI}.crop.png", b64(b"\x89PNG but not really"),
     f"{ROI}.crop", "does not decode"),
    ("image path without a folder", f"{ROI}.crop", {"path": "crop.png"}, f"{ROI}.crop",
     "needs a scene-log folder"),
    ("1-D image", f"{ROI}.mask", {"data": [1, 2, 3], "encoding": "mono8"}, f"{ROI}.mask.data",
     "2-D or 3-D"),
    ("intrinsics of 8 numbers", "camera.k", [1, 0, 0, 0, 1, 0, 0, 0], "camera.k.8", "required"),
    ("probability above 1", f"{A}.18.probability", 2, f"{A}.18.probability", "less than"),
    ("unknown log level", f"{A}.19.level", "fatal", f"{A}.19.level", "'debug'"),
    ("cluster id not hex", "clusters.1._id", "cluster-one", "clusters.1._id", "object id"),
]


@pytest.mark.parametrize("name, path, value, where, words", MALFORMED,
                         ids=[m[0] for m in MALFORMED])
def test_malformed_input_names_the_field_and_writes_nothing(store, name, path, value, where,
                                                           words):
    bad = valid_scene(seed=1, timestamp=STAMP + 1)
    container, key = at(bad, path)
    if value is DELETE:
        del container[key]
    else:
        container[key] = value
    before = snapshot(store)
    with pytest.raises(IngestError) as refused:
        IngestService(store).ingest_batch([valid_scene(seed=2, timestamp=STAMP + 2), bad])
    problems = refused.value.problems
    assert any(p["item"] == 1 and p["path"] == where for p in problems), problems
    assert words.lower() in str(refused.value).lower(), str(refused.value)
    assert all(p["item"] == 1 for p in problems)  # the valid scene is not blamed
    assert snapshot(store) == before  # nothing of the batch was written


def test_a_scene_that_is_not_an_object_is_refused(store):
    with pytest.raises(IngestError, match="JSON object, not list"):
        IngestService(store).ingest([valid_scene()])


def test_interchange_json_round_trips_exactly(store, kitchen_rgb):
    scene = synthetic.scene(np.random.default_rng(3), STAMP + 3, 3, kitchen_rgb)
    scene.images["color"] = Image(data=kitchen_rgb)
    scene.images["depth"] = Image(data=np.random.default_rng(4).random((4, 5), np.float32),
                                  encoding="32FC1")
    assign_ids(scene)  # ids travel in JSON too, so the stored scene can equal this one
    ids = IngestService(store).ingest(json.loads(scene.model_dump_json(by_alias=True)))
    assert ids.created and ids.scene_id == scene.id
    assert store.get_scene(ids.scene_id) == scene


def test_reingesting_returns_the_same_ids(store):
    service = IngestService(store)
    first = service.ingest(valid_scene(seed=5, timestamp=STAMP + 5))
    before = snapshot(store)
    again = service.ingest(valid_scene(seed=5, timestamp=STAMP + 5))
    assert (again.scene_id, again.cluster_ids) == (first.scene_id, first.cluster_ids)
    assert not again.created and snapshot(store) == before


def test_only_new_scenes_enter_the_outbox_with_their_scene(store):
    service = IngestService(store)
    first = service.ingest_batch([valid_scene(seed=6, timestamp=STAMP + 6),
                                  valid_scene(seed=7, timestamp=STAMP + 7)])
    again = service.ingest_batch([valid_scene(seed=6, timestamp=STAMP + 6)])
    entries = list(store.outbox.find({"_id": {"$in": [r.scene_id for r in first]}}))
    assert sorted(e["time"] for e in entries) == [STAMP + 6, STAMP + 7]
    assert {e["map"] for e in entries} == {store.scenes.find_one({"_id": first[0].scene_id})["map"]}
    assert not again[0].created and store.outbox.count_documents({"time": STAMP + 6}) == 1


def test_scene_log_folder_round_trip(store, tmp_path, kitchen_rgb):
    scenes = [synthetic.scene(np.random.default_rng(10 + i), STAMP + 100 + i, 2, kitchen_rgb)
              for i in range(5)]
    scenes[0].images["color"] = Image(data=kitchen_rgb)
    for scene in scenes:
        assign_ids(scene)
    assert write_scene_log(scenes, tmp_path) == 5
    assert len(list((tmp_path / "images").glob("*.png"))) == 5 * 2 * 2 + 1  # crops, masks, frame
    ingested = list(IngestService(store).ingest_stream(read_scene_log(tmp_path),
                                                       {"folder": tmp_path}))
    assert [i.ids.created for i in ingested] == [True] * 5
    for original, item in zip(scenes, ingested, strict=True):
        assert store.get_scene(item.ids.scene_id) == original


def test_scene_log_arrays_from_npy_files_and_paths_that_escape(store, tmp_path):
    vector = np.arange(308, dtype="<f4")
    np.save(tmp_path / "vfh.npy", vector)
    scene = valid_scene(seed=20, timestamp=STAMP + 200)
    scene["clusters"][0]["annotations"][7]["vector"] = {"path": "vfh.npy"}
    (tmp_path / "one.json").write_text(json.dumps(scene))
    (ingested,) = IngestService(store).ingest_stream(read_scene_log(tmp_path),
                                                     {"folder": tmp_path})
    stored = store.get_cluster(ingested.ids.cluster_ids[0]).annotations_of(FeatureVector)[0]
    assert stored.vector.tobytes() == vector.tobytes()

    (tmp_path / "one.json").unlink()
    for escape in ("../outside.png", "/etc/hostname", "images/../../x.png"):
        scene["clusters"][0]["hypotheses"][0]["crop"] = {"path": escape, "encoding": "bgr8"}
        scene["timestamp"] += 1
        (tmp_path / "bad.json").write_text(json.dumps(scene))
        with pytest.raises(IngestError, match="leaves the scene-log folder|relative file path"):
            list(IngestService(store).ingest_stream(read_scene_log(tmp_path),
                                                    {"folder": tmp_path}))


def test_scene_log_problems_name_file_and_line(store, tmp_path):
    good = json.dumps(valid_scene(seed=30, timestamp=STAMP + 300))
    (tmp_path / "log.jsonl").write_text(good + "\n" + good[: len(good) // 2] + "\n")
    with pytest.raises(IngestError, match="log.jsonl:2: .*not valid JSON"):
        list(IngestService(store).ingest_stream(read_scene_log(tmp_path)))
    (tmp_path / "empty").mkdir()
    with pytest.raises(IngestError, match="holds no .json"):
        list(read_scene_log(tmp_path / "empty"))
    with pytest.raises(IngestError, match="no such directory"):
        list(read_scene_log(tmp_path / "missing"))


def test_scene_log_reads_any_case_and_warns_of_subfolders(tmp_path, caplog):
    """RECORDING.JSON was skipped, and scenes in subfolders too, without a word."""
    (tmp_path / "RECORDING.JSON").write_text(json.dumps(valid_scene(seed=31,
                                                                    timestamp=STAMP + 310)))
    (tmp_path / "day2").mkdir()
    (tmp_path / "day2" / "b.jsonl").write_text(json.dumps(valid_scene(seed=32)) + "\n")
    with caplog.at_level(logging.WARNING):
        assert [where for where, _ in read_scene_log(tmp_path)] == ["RECORDING.JSON"]
    assert "not read: 1 scene file(s) in subfolders, such as day2/b.jsonl" in caplog.text


def test_validation_of_a_scene_object_passes_through():
    scene = Scene(timestamp=1)
    from percept_memory.ingest.service import validate

    assert validate(scene) is scene


def test_a_stream_lands_every_valid_batch_before_an_invalid_one(store):
    service = IngestService(store, batch_size=2)
    items = [(f"item {i}", valid_scene(seed=40 + i, timestamp=STAMP + 400 + i)) for i in range(5)]
    items[4][1]["timestamp"] = "later"  # the third batch is invalid
    landed = []
    with pytest.raises(IngestError, match="item 4: timestamp"):
        for ingested in service.ingest_stream(items):
            landed.append(ingested)
    assert store.scenes.count_documents(
        {"timestamp": {"$gte": STAMP + 400, "$lt": STAMP + 405}}) == 4
    queued = store.outbox.find({"time": {"$gte": STAMP + 400, "$lt": STAMP + 405}})
    assert sorted(e["time"] for e in queued) == [STAMP + 400 + i for i in range(4)]
    assert len(landed) == 4  # every stored scene is handed out before the error


def test_a_stream_repeating_a_scene_across_batches_stores_it_once(store):
    same = valid_scene(seed=50, timestamp=STAMP + 500)
    items = [("a", same), ("b", valid_scene(seed=51, timestamp=STAMP + 501)), ("c", same)]
    results = [i.ids for i in IngestService(store, batch_size=1).ingest_stream(items)]
    assert [r.created for r in results] == [True, True, False]
    assert results[0].scene_id == results[2].scene_id
    assert store.scenes.count_documents({"timestamp": STAMP + 500}) == 1


def test_a_batch_sent_in_chunks_stores_nothing_when_its_last_scene_is_invalid(store):
    """The first chunks of a batch go to the server while the rest are validated; an invalid
    scene after them abandons the transaction."""
    batch = [valid_scene(seed=60 + i, timestamp=STAMP + 600 + i) for i in range(2 * CHUNK + 1)]
    batch[-1]["timestamp"] = "yesterday"
    before = snapshot(store)
    with pytest.raises(IngestError) as refused:
        IngestService(store).ingest_batch(batch)
    assert [p["item"] for p in refused.value.problems] == [2 * CHUNK]
    assert snapshot(store) == before
    assert store.outbox.count_documents({"time": {"$gte": STAMP + 600}}) == 0


def test_a_batch_sent_in_chunks_with_scenes_stored_before_keeps_their_ids(store):
    batch = [valid_scene(seed=70 + i, timestamp=STAMP + 700 + i) for i in range(2 * CHUNK + 1)]
    stored = IngestService(store).ingest_batch(batch[CHUNK + 1 : CHUNK + 3])
    results = IngestService(store).ingest_batch(batch)
    assert [r.created for r in results] == [not CHUNK < i < CHUNK + 3 for i in range(len(batch))]
    assert results[CHUNK + 1 : CHUNK + 3] == [replace(r, created=False) for r in stored]
    assert store.scenes.count_documents({"timestamp": {"$gte": STAMP + 700}}) == len(batch)
    assert store.outbox.count_documents({"time": {"$gte": STAMP + 700}}) == len(batch)


TRANSIENT = {"errorLabels": ["TransientTransactionError"]}  # pymongo runs the transaction again


@pytest.mark.parametrize("fails", ["the second chunk's insert", "the commit"])
def test_a_chunked_batch_whose_transaction_is_run_again_is_stored_once(store, monkeypatch,
                                                                      fails):
    failures = iter([OperationFailure("write conflict", 112, TRANSIENT)])
    if fails == "the commit":
        commit = ClientSession.commit_transaction

        def flaky(session):
            if error := next(failures, None):
                session.abort_transaction()  # as the server does
                raise error
            commit(session)

        monkeypatch.setattr(ClientSession, "commit_transaction", flaky)
    else:
        insert, calls = store._insert, []

        def flaky(documents, session):
            calls.append(documents)
            if len(calls) == 2 and (error := next(failures, None)):
                raise error
            insert(documents, session)

        monkeypatch.setattr(store, "_insert", flaky)
    stamp = STAMP + (800 if fails == "the commit" else 900)
    batch = [valid_scene(seed=80 + i, timestamp=stamp + i) for i in range(2 * CHUNK + 1)]
    results = IngestService(store).ingest_batch(batch)
    assert next(failures, None) is None and all(r.created for r in results)
    assert store.scenes.count_documents({"timestamp": {"$gte": stamp, "$lt": stamp + 100}}) \
        == len(batch)


DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_the_published_schema_is_the_current_one():
    published = json.loads((DOCS / "scene.schema.json").read_text())
    assert published == Scene.model_json_schema(), "run `pmem schema > docs/scene.schema.json`"


def test_what_ingests_is_valid_by_the_published_schema_and_mistakes_are_not():
    """A robot validating before it sends (the schema's purpose) rejected the project's own
    example: an image's base64 PNG, another program's annotation."""
    import jsonschema

    schema = json.loads((DOCS / "scene.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    check = jsonschema.Draft202012Validator(schema)
    example = json.loads((DOCS / "example-scene.json").read_text())
    with_images = valid_scene(seed=3)  # (its crops and masks: base64 PNGs)
    foreign = {"_type": "acme.annotation.Grip", "force": {"$numberLong": "5"}}
    with_images["clusters"][0]["annotations"].append(foreign)
    for scene in (example, valid_scene(seed=1), with_images):
        assert not list(check.iter_errors(scene))
        Scene.model_validate(scene)  # and they ingest
    crop = ["clusters", 0, "hypotheses", 0, "crop"]
    wrong = [("no pixels", crop, {"_type": "pm.raw.Image", "encoding": "bgr8"}),
             ("two forms of pixels", [*crop, "jpeg"], "aGVsbG8="),
             ("our namespace, no such type", ["clusters", 0, "annotations", 0, "_type"],
              "pm.annotation.Bogus"),
             ("a short type name", ["clusters", 0, "annotations", 0, "_type"], "Classification"),
             ("a newline in a name", ["clusters", 0, "annotations", 1, "class_name"], "cup\nmug"),
             ("a name of 201 characters", ["robot"], "r" * 201),
             ("an escape in an image's name", ["clusters", 0, "hypotheses", 0, "image"], "\x1b"),
             ("a time before 1970", ["timestamp"], -1)]
    for name, path, value in wrong:
        scene = json.loads(json.dumps(with_images))
        *parents, last = path
        target = scene
        for key in parents:
            target = target[key]
        target[last] = value
        assert list(check.iter_errors(scene)), name


def test_the_published_example_ingests(store):
    example = json.loads((DOCS / "example-scene.json").read_text())
    ids = IngestService(store).ingest(example)
    stored = store.get_scene(ids.scene_id)
    assert stored.clusters[0].annotations[-1].type_name == "lab.annotation.Weight"
    assert stored.clusters[0].hypotheses[0].crop.data.shape == (8, 8, 3)


def test_an_unknown_types_extended_json_values_are_stored_as_the_bson_values(store):
    scene = valid_scene(seed=8, timestamp=STAMP + 80)
    scene["clusters"][0]["annotations"].append({
        "_type": "lab.annotation.Ref", "object": {"$oid": "5f0000000000000000000001"},
        "raw": {"$binary": {"base64": "AP8=", "subType": "00"}}, "count": {"$numberLong": "5"},
        "note": {"text": "plain objects stay objects"}})
    ids = IngestService(store).ingest(json.loads(json.dumps(scene)))
    stored = store.clusters.find_one({"_id": ids.cluster_ids[0]})["annotations"][-1]
    assert stored["object"] == ObjectId("5f0000000000000000000001")
    assert stored["raw"] == b"\x00\xff" and type(stored["count"]) is Int64
    assert stored["note"] == {"text": "plain objects stay objects"}


@pytest.mark.parametrize("fmt, extension", [("png", ".png"), ("jpeg", ".jpg")])
def test_an_image_given_as_a_file_is_stored_as_that_file_and_reads_back_exactly(
        store, kitchen_rgb, fmt, extension):
    file = cv2.imencode(extension, kitchen_rgb[100:164, 200:264])[1].tobytes()
    scene = valid_scene(seed=7, timestamp=STAMP + 70 + len(fmt))
    scene["images"] = {"color": {fmt: b64(file), "encoding": "bgr8"}}
    ids = IngestService(store).ingest(scene)
    stored = store.scenes.find_one({"_id": ids.scene_id})["images"]["color"]
    assert store.get_blob(stored["data"]["_blob"]) == file  # not decoded and encoded again
    read = store.get_scene(ids.scene_id).images["color"]
    assert np.array_equal(read.data, cv2.imdecode(np.frombuffer(file, np.uint8),
                                                  cv2.IMREAD_UNCHANGED))


def test_an_image_whose_pixels_changed_is_encoded_again(kitchen_rgb):
    file = cv2.imencode(".png", kitchen_rgb[:64, :64])[1].tobytes()
    image = Image.model_validate({"png": b64(file)}, context={})
    assert image.file == file
    with pytest.raises(ValueError):  # the pixels of a file are not changed in place
        image.data[0, 0] = 0
    image.data = kitchen_rgb[64:128, :64]
    assert image.file is None
    image = Image.model_validate({"png": b64(file), "format": "jpeg"}, context={})
    assert image.file is None
