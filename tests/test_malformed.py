"""The malformed corpus: a valid scene spoilt in one way per case (wrong types, missing and
unknown fields, hostile strings, huge numbers, bad base64, images and arrays, duplicate ids,
...). Sent to POST /api/scenes, each gets a 4xx in the one error shape naming the field, and
nothing is stored; imported with `pmem import scene-log`, each exits 1 with one line
`Error: ...` naming the field, and nothing is stored."""

from __future__ import annotations

import base64
import copy
import json
import struct

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st

from percept_memory.answers import printable
from percept_memory.ingest.json_input import MAX_STRING, input_problems, parse, screened
from percept_memory.memory.settings import Settings
from percept_memory.memory.types.base import MAX_TIMESTAMP
from percept_memory.webui.app import create_app

from .conftest import LOCAL
from .test_cli import error_line, pmem
from .test_ingest import MALFORMED, STAMP, valid_scene

DELETE = MALFORMED[0][2]  # the marker test_ingest's table uses for "remove this field"
A = "clusters.0.annotations"
ROI, CROP = "clusters.0.hypotheses.0", "clusters.0.hypotheses.0.crop"
NEW = f"{A}.20"  # an annotation appended after the scene's 20
LONG = "x" * (2**20 + 1)  # one character over a text's limit
SCENE = valid_scene(seed=1, timestamp=STAMP + 1)
ONE_ID = "5f0000000000000000000001"


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def png(height: int, width: int) -> str:
    return b64(cv2.imencode(".png", np.zeros((height, width), np.uint8))[1].tobytes())


def nested(depth: int):
    return [nested(depth - 1)] if depth else []


def image(**fields) -> dict:
    return {"encoding": "bgr8", **fields}


# (name, path, new value or DELETE, the path the error must name)
CORPUS = [(name, path, value, where) for name, path, value, where, _ in MALFORMED] + [
    # hostile strings and field names
    ("lone surrogate in the robot", "robot", "a\ud800b", "robot"),
    ("lone surrogate in the frame", "frame", "\udfff", "frame"),
    ("lone surrogate in a source", f"{A}.0.source", "x\udc00", f"{A}.0.source"),
    ("lone surrogate in a text", f"{A}.8.text", "Lipton\ud800", f"{A}.8.text"),
    ("lone surrogate in a field name", f"{A}.11.properties", {"\ud800": 1},
     f"{A}.11.properties"),
    ("NUL in a field name", NEW, {"_type": "lab.annotation.Weight", "a\0b": 1}, NEW),
    ("$ field name", NEW, {"_type": "lab.annotation.Weight", "$where": "1"}, NEW),
    ("$ key in a mapping", f"{A}.11.properties.$set", 1, f"{A}.11.properties"),
    ("malformed Extended JSON id", NEW, {"_type": "lab.annotation.Ref", "id": {"$oid": "zz"}},
     f"{NEW}.id"),
    ("Extended JSON with a field more", NEW,
     {"_type": "lab.annotation.Ref", "id": {"$oid": ONE_ID, "x": 1}}, f"{NEW}.id"),
    ("Extended JSON code, which is not read", NEW,
     {"_type": "lab.annotation.Ref", "f": {"$code": "x"}}, f"{NEW}.f"),
    ("Extended JSON id where a text belongs", f"{A}.0.source", {"$oid": ONE_ID}, f"{A}.0.source"),
    ("Extended JSON long beyond 64 bits", NEW,
     {"_type": "lab.annotation.X", "v": {"$numberLong": "99999999999999999999"}}, f"{NEW}.v"),
    ("Extended JSON int beyond 32 bits", NEW,
     {"_type": "lab.annotation.X", "v": {"$numberInt": "99999999999"}}, f"{NEW}.v"),
    ("Extended JSON decimal not a number", NEW,
     {"_type": "lab.annotation.X", "v": {"$numberDecimal": "abc"}}, f"{NEW}.v"),
    ("Extended JSON nested too deeply", NEW,
     {"_type": "lab.annotation.Ref", "v": {"$oid": nested(900)}}, f"{NEW}.v"),
    ("NUL in a mapping key", f"{A}.1.confidences.a\0", 0.1, f"{A}.1.confidences"),
    ("robot name too long", "robot", "r" * 201, "robot"),
    ("map name too long", "map", "m" * 201, "map"),
    ("frame name too long", "frame", "f" * 1000, "frame"),
    ("text over a MiB", f"{A}.8.text", LONG, f"{A}.8.text"),
    ("log message over a MiB", "log.0.message", LONG, "log.0.message"),
    ("unknown field over a MiB", NEW, {"_type": "lab.annotation.Note", "v": LONG}, f"{NEW}.v"),
    # type names
    ("empty type name", NEW, {"_type": ""}, NEW),
    ("$ type name", NEW, {"_type": "$where"}, NEW),
    ("path as type name", NEW, {"_type": "../../etc/passwd"}, NEW),
    ("type name with two dots", NEW, {"_type": "lab..Weight"}, NEW),
    ("type name with a space", NEW, {"_type": "lab.annotation Weight"}, NEW),
    ("type name too long", NEW, {"_type": "lab." + "w" * 300}, NEW),
    ("type name null", f"{A}.1._type", None, f"{A}.1"),
    ("unknown type in our namespace", f"{ROI}._type", "pm.hypothesis.Blob", ROI),
    ("scene of another type", "_type", "pm.scene.Cluster", "_type"),
    ("view region of the wrong kind", "view_region",
     {"_type": "pm.hypothesis.ImageROI", "box": [0, 0, 1, 1]}, "view_region"),
    # nesting
    ("900 levels in an unknown annotation", NEW,
     {"_type": "lab.annotation.Deep", "v": nested(900)}, f"{NEW}.v"),
    ("40 levels in a property", f"{A}.11.properties.deep", nested(40),
     f"{A}.11.properties.deep"),
    # numbers
    ("timestamp true", "timestamp", True, "timestamp"),
    ("timestamp false", "timestamp", False, "timestamp"),
    ("timestamp with a fraction", "timestamp", 1.5, "timestamp"),
    ("timestamp a nanosecond past 2262-04-11T23:47:16Z", "timestamp", MAX_TIMESTAMP + 1,
     "timestamp"),
    ("timestamp 1e30", "timestamp", 1e30, "timestamp"),
    ("timestamp null", "timestamp", None, "timestamp"),
    ("confidence as a word", f"{A}.1.confidence", "high", f"{A}.1.confidence"),
    ("box of five numbers", f"{ROI}.box", [0, 0, 1, 1, 1], f"{ROI}.box"),
    ("box with a fraction", f"{ROI}.box.0", 1.5, f"{ROI}.box.0"),
    ("box past int64", f"{ROI}.box.2", 2**64, f"{ROI}.box.2"),
    ("tracking id past int64", f"{A}.16.tracking_id", 2**70, f"{A}.16.tracking_id"),
    ("property past int64", f"{A}.11.properties.weight_g", -(2**64),
     f"{A}.11.properties.weight_g"),
    ("image width zero", "camera.width", 0, "camera.width"),
    ("image height negative", "camera.height", -480, "camera.height"),
    ("NaN in the intrinsics", "camera.k.0", float("nan"), "camera.k.0"),
    ("rotation of length 2", "camera_pose.rotation", [0, 0, 0, 2.0], "camera_pose.rotation"),
    ("translation of words", "camera_pose.translation", ["a", "b", "c"],
     "camera_pose.translation.0"),
    ("volume as a word", f"{A}.17.volume", "big", f"{A}.17.volume"),
    ("size of two numbers", f"{A}.17.size", [1, 2], f"{A}.17.size"),
    ("negative probability", f"{A}.18.probability", -1, f"{A}.18.probability"),
    ("duration as a word", f"{A}.19.duration_ms", "slow", f"{A}.19.duration_ms"),
    # missing and unknown fields
    ("intrinsics missing", "camera.k", DELETE, "camera.k"),
    ("box missing", f"{ROI}.box", DELETE, f"{ROI}.box"),
    ("child frame missing", "camera_pose.child_frame", DELETE, "camera_pose.child_frame"),
    ("predicate missing", f"{A}.18.predicate", DELETE, f"{A}.18.predicate"),
    ("unknown cluster field", "clusters.0.colour", "red", "clusters.0.colour"),
    ("unknown camera field", "camera.colour", "red", "camera.colour"),
    ("unknown hypothesis field", f"{ROI}.colour", "red", f"{ROI}.colour"),
    ("unknown image field", f"{CROP}.colour", "red", CROP),
    ("unknown log field", "log.0.colour", "red", "log.0.colour"),
    # wrong shapes
    ("clusters an object", "clusters", {"a": 1}, "clusters"),
    ("clusters a text", "clusters", "many", "clusters"),
    ("cluster a number", "clusters.0", 5, "clusters.0"),
    ("hypotheses null", "clusters.0.hypotheses", None, "clusters.0.hypotheses"),
    ("images a list", "images", [], "images"),
    ("log a text", "log", "all fine", "log"),
    ("camera a list", "camera", [640, 480], "camera"),
    ("transforms an object", "transforms", {"a": 1}, "transforms"),
    ("relation a number", "relations", [1], "relations.0"),
    ("confidence map of words", f"{A}.1.confidences.cereal", "high",
     f"{A}.1.confidences.cereal"),
    ("links a text", f"{A}.13.links", "https://example.org", f"{A}.13.links"),
    ("properties a list", f"{A}.11.properties", [1, 2], f"{A}.11.properties"),
    ("too many clusters", "clusters", [{}] * 1001, "clusters"),
    # ids
    ("two clusters with one id", "clusters", [dict(c, _id=ONE_ID) for c in SCENE["clusters"]],
     "clusters"),
    ("two annotations with one id", A,
     [dict(a, _id=ONE_ID) for a in SCENE["clusters"][0]["annotations"][:2]], A),
    ("annotation id not hex", f"{A}.1._id", "one", f"{A}.1._id"),
    ("scene id of a cluster not hex", "clusters.0.scene_id", "x", "clusters.0.scene_id"),
    ("object id of 25 digits", "clusters.0.object_id", "5" * 25, "clusters.0.object_id"),
    ("scene id not hex", "_id", "zz", "_id"),
    # images
    ("empty png", f"{CROP}.png", "", CROP),
    ("png not base64", f"{CROP}.png", "@@@", CROP),
    ("png that is a GIF", f"{CROP}.png", b64(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;"), CROP),
    ("png that is a BMP", f"{CROP}.png",
     b64(cv2.imencode(".bmp", np.zeros((2, 2), np.uint8))[1].tobytes()), CROP),
    ("jpeg that is noise", f"{CROP}", image(jpeg=b64(b"\xff\xd8\xff\xe0 noise")), CROP),
    ("16000 x 16000 scene image", "images.color", image(png=png(16000, 16000),
                                                        encoding="mono8"), "images.color"),
    ("2500 x 2500 crop", CROP, image(png=png(2500, 2500), encoding="mono8"), CROP),
    ("JPEG whose header says 20000 x 20000", CROP, image(jpeg=b64(
        b"\xff\xd8\xff\xc0" + struct.pack(">HBHHB", 11, 8, 20_000, 20_000, 1) + b"\0" * 3)),
     CROP),
    ("crop without pixels", CROP,
     image(data={"dtype": "|u1", "shape": [0, 0, 3], "base64": ""}), f"{CROP}.data"),
    ("crop as png and path", f"{CROP}.path", "crop.png", CROP),
    ("crop as png and data", f"{CROP}.data", [[1]], CROP),
    ("4-D mask", f"{ROI}.mask", {"data": [[[[1]]]], "encoding": "mono8"}, f"{ROI}.mask.data"),
    ("absolute image path", CROP, image(path="/etc/passwd"), CROP),
    ("image path leaving the folder", CROP, image(path="../x.png"), CROP),
    ("image format gif", f"{CROP}.format", "gif", f"{CROP}.format"),
    ("image of words", CROP, image(data=[["a"]]), f"{CROP}.data"),
    # arrays
    ("array of objects", f"{A}.7.vector.dtype", "|O", f"{A}.7.vector"),
    ("array of empty items", f"{A}.7.vector.dtype", "|V0", f"{A}.7.vector"),
    ("negative shape", f"{A}.7.vector.shape", [-308], f"{A}.7.vector"),
    ("shape not a list", f"{A}.7.vector.shape", 308, f"{A}.7.vector"),
    ("array with an extra key", f"{A}.7.vector.order", "C", f"{A}.7.vector"),
    ("array without bytes", f"{A}.7.vector.base64", DELETE, f"{A}.7.vector"),
    ("ragged histogram", f"{A}.6.histogram", [[1.0], [1.0, 2.0]], f"{A}.6.histogram"),
    ("cloud of 2-D points", "clouds.scene", {"points": [[1.0, 2.0]]}, "clouds.scene.points"),
    ("cloud without points", "clouds.scene", {"frame": "map"}, "clouds.scene.points"),
]
# (name, file or body text, words of the message)
TEXTS = [
    ("not JSON", "{scene", "not valid JSON"),
    ("JSON nested 100000 deep", "[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ("a scene that is a number", "5", "JSON object"),
    ("half a scene", '{"timestamp": 1', "not valid JSON"),
]


def spoilt(path: str, value) -> dict:
    """A valid scene with the value at `path` replaced (DELETE: removed; one past the end of
    a list: appended)."""
    scene = copy.deepcopy(SCENE)
    *parents, last = path.split(".")
    container = scene
    for part in parents:
        container = container[int(part)] if isinstance(container, list) else container[part]
    key = int(last) if isinstance(container, list) else last
    if value is DELETE:
        del container[key]
    elif isinstance(container, list) and key == len(container):
        container.append(value)
    else:
        container[key] = value
    return scene


def counts(store) -> dict:
    return {name: store.db[name].count_documents({})
            for name in ("scenes", "clusters", "outbox", "types", "fs.files")}


@pytest.fixture(scope="module")
def client(store):
    return TestClient(create_app(store, Settings(consolidator=False)), base_url=LOCAL)


def test_the_corpus_is_large_and_every_case_is_named_once():
    names = [case[0] for case in CORPUS + TEXTS]
    assert len(names) >= 100 and len(set(names)) == len(names)


def refused_over_http(client, store, body: str) -> dict:
    before = counts(store)
    response = client.post("/api/scenes", content=body,
                           headers={"content-type": "application/json"})
    assert response.status_code in (413, 415, 422), response.text
    error = response.json()["error"]
    assert error["status"] == response.status_code
    assert counts(store) == before
    return error


@pytest.mark.parametrize("name, path, value, where", CORPUS, ids=[c[0] for c in CORPUS])
def test_post_refuses_the_case_by_name_and_stores_nothing(client, store, name, path, value,
                                                          where):
    error = refused_over_http(client, store, json.dumps(spoilt(path, value)))
    named = [p for p in error["problems"] if where in p["path"] or where in p["message"]]
    assert named, error


@pytest.mark.parametrize("name, text, words", TEXTS, ids=[t[0] for t in TEXTS])
def test_post_refuses_what_is_not_a_scene(client, store, name, text, words):
    assert words in json.dumps(refused_over_http(client, store, text))


def refused_by_import(tmp_path, mongo_uri, db_name, store, text: str) -> str:
    (tmp_path / "scene.json").write_text(text, encoding="utf-8")
    before = counts(store)
    line = error_line(pmem("import", "scene-log", str(tmp_path), MONGODB_URI=mongo_uri,
                           PMEM_DB=db_name))
    assert counts(store) == before
    return line


@pytest.mark.parametrize("name, path, value, where", CORPUS, ids=[c[0] for c in CORPUS])
def test_import_refuses_the_case_by_name_in_one_line_and_stores_nothing(
        tmp_path, mongo_uri, db_name, store, name, path, value, where):
    line = refused_by_import(tmp_path, mongo_uri, db_name, store,
                             json.dumps(spoilt(path, value)))
    assert printable(where) in line  # (a control character in it as its escape)


@pytest.mark.parametrize("name, text, words", TEXTS, ids=[t[0] for t in TEXTS])
def test_import_refuses_what_is_not_a_scene(tmp_path, mongo_uri, db_name, store, name, text,
                                            words):
    line = refused_by_import(tmp_path, mongo_uri, db_name, store, text)
    assert "scene.json" in line and words in line


# --- the screen of raw bytes that lets valid input skip the walk of json_input ----------------

EDGES = st.sampled_from(["$", "$x", "a\0b", "\ud800", "x" * 40, "9" * 19, "[", "]", "{", "\\"])
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.floats(allow_nan=False)
    | st.integers(-(2**66), 2**66) | st.sampled_from([2**63 - 1, 2**63, -(2**63), -(2**63) - 1])
    | st.text(max_size=8) | EDGES,
    lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.text(max_size=4) | EDGES, inner, max_size=4),
    max_leaves=40)


def bodies(data) -> list[bytes]:
    """The data as a scene and as a batch of one, compact, spaced and with text unescaped."""
    texts = [json.dumps(data), json.dumps(data, indent=1), json.dumps(data, ensure_ascii=False)]
    return [encoded for text in texts
            for encoded in (text.encode("utf-8", "surrogatepass"),
                            f"[{text}]".encode("utf-8", "surrogatepass"))]


@pytest.mark.parametrize("name, path, value, where", CORPUS, ids=[c[0] for c in CORPUS])
def test_the_screen_never_passes_what_the_walk_refuses(name, path, value, where):
    data = spoilt(path, value)
    if input_problems(data):
        assert not any(map(screened, bodies(data)))


@settings(max_examples=400, deadline=None)
@given(JSON_VALUES, st.integers(1, 40))
def test_the_screen_never_passes_what_the_walk_refuses_random(value, depth):
    data = {"v": value, "deep": nested(depth)}
    if input_problems(data):  # the walk of a batch walks each scene
        assert not any(map(screened, bodies(data)))


def test_a_valid_scene_passes_the_screen_and_parses_as_json_does():
    for body in bodies(SCENE):
        assert screened(body)
        assert parse(body) == (json.loads(body), True)


@pytest.mark.parametrize("padding", [0, 1, 7, MAX_STRING // 2 - 3, MAX_STRING // 2 + 5])
def test_the_screen_measures_a_string_at_any_place_and_passes_long_unquoted_stretches(padding):
    ones = [1] * (MAX_STRING // 2)  # a stretch of MAX_STRING bytes without a quote
    for length, passes in ((MAX_STRING, True), (MAX_STRING + 1, False)):
        data = {"p": "x" * padding, "t": "y" * length, "n": ones}
        body = json.dumps(data, separators=(",", ":")).encode()
        assert screened(body) is passes
        assert bool(input_problems(data)) is not passes
    assert screened(json.dumps({"n": ones, "p": "x" * padding}).encode())
