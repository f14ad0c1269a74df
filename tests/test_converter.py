"""The generic codec: lossless round trips for every registered type, through real BSON bytes."""

from __future__ import annotations

import json
from datetime import datetime

import bson
import cv2
import numpy as np
import pytest
from bson import Decimal128, Int64, ObjectId
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from percept_memory.converters import (
    ConversionError,
    DecodeContext,
    EncodeContext,
    Unknown,
    decode,
    encode,
    register_type,
    registered_types,
)
from percept_memory.converters.images import image_size
from percept_memory.memory.types import (
    Classification,
    Cluster,
    FeatureVector,
    Image,
    ImageROI,
    Location,
    Model,
    Product,
    Scene,
    Shape,
    Text,
)

from .strategies import for_model


def round_trip(value, threshold: int = 1024):
    """encode -> BSON bytes -> decode, with a small blob threshold so blobs are exercised."""
    ctx = EncodeContext(threshold=threshold)
    raw = bson.encode(encode(value, ctx))
    return decode(bson.decode(raw), DecodeContext(ctx.blobs))


@pytest.mark.parametrize("type_name", sorted(registered_types()))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_registered_type_round_trips(type_name, data):
    value = data.draw(for_model(registered_types()[type_name]))
    back = round_trip(value)
    assert type(back) is type(value)
    assert back == value


EDGE_CASES = {
    "nan-negzero-inf": np.array([np.nan, -0.0, 0.0, np.inf, -np.inf], dtype="<f8"),
    "big-endian": np.array([1.5, -0.0, np.nan], dtype=">f4"),  # stays big-endian
    "0-d": np.array(3.25),
    "empty": np.zeros((0, 3), dtype=np.float32),
    "strided": np.arange(24, dtype=np.int16).reshape(2, 3, 4)[:, ::2, ::-1],
    "fortran": np.asfortranarray(np.arange(6, dtype=np.uint8).reshape(2, 3)),
    "structured": np.array([(1.0, 2.0, 3.0, 0xFF00FF)],
                           dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")]),
    "structured-subarray": np.frombuffer(bytes(range(48)), dtype=[
        ("xyz", "<f4", (3,)), ("rgb", "<u4"), ("n", [("ij", ">i2", (2,))], (2,))]),
    "complex": np.array([1 + 2j, np.nan * 1j], dtype="<c16"),
}


def same_bits(back: np.ndarray, array: np.ndarray) -> None:
    assert back.dtype == array.dtype
    assert back.shape == array.shape
    assert back.tobytes() == np.ascontiguousarray(array).tobytes()
    assert back.flags.writeable


@pytest.mark.parametrize("array", EDGE_CASES.values(), ids=EDGE_CASES.keys())
def test_numpy_edge_cases_are_bit_exact(array):
    same_bits(round_trip(FeatureVector(name="v", vector=array)).vector, array)


@pytest.mark.parametrize("array", EDGE_CASES.values(), ids=EDGE_CASES.keys())
def test_numpy_edge_cases_are_bit_exact_through_json(array):
    text = FeatureVector(name="v", vector=array).model_dump_json()
    same_bits(FeatureVector.model_validate_json(text).vector, array)


def test_nan_payload_survives():
    payload = np.array([0x7FF8_0000_DEAD_BEEF], dtype="<u8").view("<f8")
    back = round_trip(FeatureVector(name="v", vector=payload)).vector
    assert back.view("<u8")[0] == 0x7FF8_0000_DEAD_BEEF


def test_array_over_16_mb_leaves_the_document():
    big = np.random.default_rng(1).random(2_200_000)  # 17.6 MB of float64
    ctx = EncodeContext(threshold=128 * 1024)
    doc = encode(FeatureVector(name="big", vector=big), ctx)
    assert len(bson.encode(doc)) < 1024
    assert [len(b) for b in ctx.blobs.values()] == [big.nbytes]
    back = decode(bson.decode(bson.encode(doc)), DecodeContext(ctx.blobs))
    assert back.vector.tobytes() == big.tobytes()


def test_object_arrays_are_refused_with_the_field_named():
    vector = FeatureVector.model_construct(name="v", vector=np.array([object()]))
    with pytest.raises(ConversionError, match=r"pm.annotation.FeatureVector.vector: .*objects"):
        encode(vector)


def test_python_object_arrays_are_refused_on_input():
    with pytest.raises(ValidationError, match="numbers"):
        FeatureVector(name="v", vector=[{"a": 1}])


@pytest.mark.parametrize(
    "shape, dtype, encoding",
    [((48, 64, 3), np.uint8, "rgb8"), ((48, 64, 3), np.uint8, "bgr8"), ((48, 64), np.uint8,
     "mono8"), ((48, 64), np.uint16, "mono16"), ((48, 64, 4), np.uint8, "rgba8"),
     ((48, 64, 1), np.uint16, "16UC1")],
)
def test_png_images_are_bit_exact_and_real_png(shape, dtype, encoding):
    rng = np.random.default_rng(7)
    array = rng.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype)
    ctx = EncodeContext()
    doc = encode(Image(data=array, encoding=encoding), ctx)
    assert doc["stored_as"] == "png"
    assert doc["data"][:8] == b"\x89PNG\r\n\x1a\n"
    back = decode(doc, DecodeContext(ctx.blobs))
    assert back.data.dtype == array.dtype and np.array_equal(back.data, array)
    # The PNG file itself has the right colours: OpenCV reads it back as BGR.
    on_disk = cv2.imdecode(np.frombuffer(doc["data"], np.uint8), cv2.IMREAD_UNCHANGED)
    if encoding.startswith("rgb"):  # red and blue trade places, alpha stays
        expected = array[..., [2, 1, 0, 3][: shape[2]]]
    else:
        expected = array.reshape(on_disk.shape)
    assert np.array_equal(on_disk, expected)


def test_real_kitchen_png_round_trips_bit_exact(kitchen_rgb):
    image = Image(data=kitchen_rgb, encoding="bgr8")
    back = round_trip(image, threshold=64 * 1024)
    assert back == image


def test_images_png_cannot_hold_are_stored_raw():
    depth = np.random.default_rng(3).random((8, 8)).astype(np.float32)
    doc = encode(Image(data=depth, encoding="32FC1"))
    assert doc["stored_as"] == "raw"
    assert np.array_equal(decode(doc).data, depth)


def test_jpeg_on_request():
    gradient = np.tile(np.arange(64, dtype=np.uint8), (32, 1))
    doc = encode(Image(data=np.dstack([gradient] * 3), format="jpeg"))
    assert doc["data"][:2] == b"\xff\xd8"
    back = decode(doc)
    assert back.format == "jpeg"
    assert np.abs(back.data.astype(int) - np.dstack([gradient] * 3)).max() <= 4


def test_nested_unions_resolve_by_type():
    cluster = Cluster(
        hypotheses=[ImageROI(box=(1, 2, 3, 4), phash="00ff00ff00ff00ff")],
        annotations=[
            Classification(class_name="cup", confidences={"cup": 0.9, "mug": 0.1}),
            Shape(shape="cylinder", confidence=0.7),
            Product(name="Pringles", properties={"weight.g": 165, "$price": "2.49", "vegan": True,
                                                 "rating": 4.5, "100%": "yes"}),
            Unknown(type_name="rs.annotation.Hologram", fields={"depth": 3}),
        ],
    )
    back = round_trip(Scene(timestamp=1, clusters=[cluster]))
    kinds = [type(a) for a in back.clusters[0].annotations]
    assert kinds == [Classification, Shape, Product, Unknown]
    assert back.clusters[0].annotations[2].properties == cluster.annotations[2].properties
    assert type(back.clusters[0].annotations[2].properties["vegan"]) is bool


def test_dict_keys_that_mongodb_forbids_are_escaped():
    doc = encode(Product(properties={"a.b": "1", "$c": "2", "d%2E": "3"}))
    assert set(doc["properties"]) == {"a%2Eb", "%24c", "d%252E"}


def test_unknown_type_keeps_every_field_and_writes_back_unchanged():
    stored = {
        "_type": "rs.annotation.Hologram",
        "_id": ObjectId(),
        "_parent": ObjectId(),
        "depth": 3,
        "data": b"\x00\x01",
        "nested": {"_type": "rs.cv.Mat", "rows": 2, "cols": 1, "data": b"\x05\x06"},
        "list": [1, "two", {"three": 3.0}],
    }
    value = decode(stored)
    assert isinstance(value, Unknown) and value.type_name == "rs.annotation.Hologram"
    assert bson.encode(encode(value)) == bson.encode(stored)


def test_an_unknown_type_travels_through_json_as_extended_json_and_comes_back_unchanged():
    stored = {
        "_type": "rs.annotation.Hologram",
        "_id": ObjectId(),
        "depth": 3,
        "wide": Int64(3),
        "data": b"\x00\xff",
        "when": datetime(2026, 11, 29, 3, 4, 5, 6000),
        "exact": Decimal128("0.1"),
        "nested": [{"_type": "rs.cv.Mat", "parent": ObjectId(), "cells": [Int64(2**40)]}],
    }
    text = decode(stored).model_dump_json()
    assert json.loads(text)["_id"] == {"$oid": str(stored["_id"])}
    assert json.loads(text)["wide"] == {"$numberLong": "3"}
    back = Unknown.model_validate_json(text)
    assert bson.encode(encode(back)) == bson.encode(stored)
    assert type(back.fields["wide"]) is Int64 and type(back.fields["depth"]) is int


def test_fields_a_newer_version_wrote_are_kept():
    stored = encode(Shape(shape="box"))
    stored["added_in_v9"] = {"x": 1}
    value = decode(stored)
    assert value.shape == "box"
    assert encode(value)["added_in_v9"] == {"x": 1}


def test_unreadable_known_type_becomes_unknown_with_the_problem():
    stored = encode(FeatureVector(name="v", vector=np.zeros(4, np.float32)))
    stored["vector"]["shape"] = [5]  # 16 bytes cannot be 5 float32s
    value = decode(stored)
    assert isinstance(value, Unknown)
    assert "vector" in value.problem
    assert encode(value) == stored


def test_missing_required_field_becomes_unknown():
    value = decode({"_type": "pm.annotation.Text", "source": "ocr"})
    assert isinstance(value, Unknown) and "text" in value.problem


def test_aliases_resolve_foreign_names():
    value = decode({"_type": "rs.annotation.Shape", "shape": "box", "confidence": 0.5,
                    "source": "PrimitiveShapeAnnotator"})
    assert isinstance(value, Shape) and value.shape == "box"
    assert encode(value)["_type"] == "pm.annotation.Shape"


def test_a_new_type_needs_no_converter_code():
    @register_type("test.annotation.Weight")
    class Weight(Model):
        grams: float
        scale: str = "kitchen"
        history: list[tuple[int, float]] = []

    value = Weight(grams=412.5, history=[(1, 400.0), (2, 412.5)])
    assert round_trip(value) == value


def test_containers_annotated_without_their_items_store_too():
    """`props: dict` was an IndexError deep in the codec (it read dict[Any]'s second type)."""
    @register_type("test.annotation.Bare")
    class Bare(Model):
        props: dict = {}
        tags: list = []
        pair: tuple = ()
        kinds: set = set()

    value = Bare(props={"a": 1, "b": [2.5, "c"]}, tags=[1, "x"], pair=(1, "y"), kinds={"k"})
    assert round_trip(value) == value


def test_unregistered_class_is_refused_clearly():
    class Loose(Text):
        pass

    with pytest.raises(ConversionError, match="Loose is not a registered type"):
        encode(Loose(text="x"))


def test_validation_dispatches_on_type_and_names_the_field():
    cluster = Cluster.model_validate(
        {"annotations": [{"_type": "pm.annotation.Location", "region": "sink",
                          "position": [1, 2, 3]}]}
    )
    assert isinstance(cluster.annotations[0], Location)
    with pytest.raises(ValidationError, match=r"annotations\.0"):
        Cluster.model_validate(
            {"annotations": [{"_type": "pm.annotation.Location", "position": [1, "x", 3]}]}
        )


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
@pytest.mark.parametrize("shape", [(480, 640, 3), (7, 1, 3), (1, 3000)])
def test_image_sizes_are_read_from_the_header(suffix, shape):
    encoded = cv2.imencode(suffix, np.zeros(shape, np.uint8))[1].tobytes()
    assert image_size(encoded) == (shape[1], shape[0])
    assert image_size(b"GIF89a") is None and image_size(encoded[:3]) is None
