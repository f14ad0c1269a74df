"""Exports read back by real readers: pycocotools loads COCO, YOLO label files are checked
against their images, every image decodes with OpenCV, and the counts and labels are those of
the store (read from the raw documents, not through the exporter).

Data: the kitchen week ingested with consolidation (crops, classifications, object names),
synthetic scenes on the real kitchen frame (whole scene images with boxes and masks) and the
real RoboSherlock PnP09 objects (ground-truth labels, VFH and CNN features, no pixels).
"""

from __future__ import annotations

import gc
import io
import json
import os
import subprocess
import sys
import zipfile
from collections import Counter
from pathlib import Path

import bson
import cv2
import numpy as np
import pytest
import yaml
from bson import ObjectId
from click.testing import CliRunner
from fastapi.testclient import TestClient
from pycocotools.coco import COCO

from percept_memory.cli import main
from percept_memory.ingest import synthetic
from percept_memory.ingest.robosherlock import read_dump
from percept_memory.ingest.service import IngestService
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import Classification, Image
from percept_memory.queries.export.model import ExportQuery
from percept_memory.queries.export.run import Export
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ROBOSHERLOCK

PNP = ROBOSHERLOCK / "mongodump" / "PnP09ObjSymbolicGTFixed"
CLASSIFICATION = "pm.annotation.Classification"
SYNTH_SCENES, SYNTH_CLUSTERS = 4, 6
pytestmark = pytest.mark.filterwarnings(  # pycocotools on numpy 2
    "ignore:__array__ implementation doesn't accept a copy keyword:DeprecationWarning")


@pytest.fixture(scope="module")
def memory(store, kitchen, kitchen_rgb):
    """The kitchen week (robot pr2), synthetic scenes with the real frame as their image
    (robot synth) and PnP09 (robot pnp09), in the module's store."""
    rng = np.random.default_rng(7)
    scenes = []
    for i in range(SYNTH_SCENES):
        scene = synthetic.scene(rng, 1_600_000_000_000_000_000 + i, SYNTH_CLUSTERS,
                                kitchen_rgb, robot="synth")
        scene.images = {"color": Image(data=kitchen_rgb, encoding="bgr8")}
        scenes.append(scene)
    scenes += read_dump(PNP, robot="pnp09")
    list(IngestService(store).ingest_stream((str(i), s) for i, s in enumerate(scenes)))
    return store


def exported(store, **query) -> tuple[bytes, zipfile.ZipFile]:
    data = b"".join(Export(store, ExportQuery(**query)).zip_stream())
    return data, zipfile.ZipFile(io.BytesIO(data))


def lines(archive: zipfile.ZipFile, name: str) -> list[dict]:
    return [json.loads(line) for line in archive.read(name).splitlines()]


def decoded(archive: zipfile.ZipFile, name: str) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(archive.read(name), np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None, name
    return image


def classified(store, robot: str) -> Counter:
    """Class name -> clusters, from the raw documents (each cluster's most confident one)."""
    counts = Counter()
    for doc in store.clusters.find({"search.robot": robot, "annotations._type": CLASSIFICATION}):
        found = [a for a in doc["annotations"] if a["_type"] == CLASSIFICATION]
        counts[max(found, key=lambda a: a.get("confidence") or -1)["class_name"]] += 1
    return counts


# --- COCO -----------------------------------------------------------------------------------


def test_coco_crops_of_the_kitchen_week_load_in_pycocotools(memory, tmp_path):
    _, archive = exported(memory, format="coco", images="crops", robot=["pr2"])
    (tmp_path / "annotations.json").write_bytes(archive.read("annotations.json"))
    coco = COCO(str(tmp_path / "annotations.json"))
    expected = classified(memory, "pr2")
    assert len(coco.getAnnIds()) == len(coco.getImgIds()) == expected.total() > 100
    assert Counter(coco.cats[a["category_id"]]["name"] for a in coco.anns.values()) == expected
    stored = memory.get_clusters([ObjectId(a["cluster_id"]) for a in coco.anns.values()])
    for annotation in coco.anns.values():
        image = coco.imgs[annotation["image_id"]]
        pixels = decoded(archive, f"images/{image['file_name']}")
        assert pixels.shape[:2] == (image["height"], image["width"])
        (roi,) = stored[ObjectId(annotation["cluster_id"])].hypotheses
        assert np.array_equal(pixels, roi.crop.data)  # the stored crop, bit for bit
        mask = coco.annToMask(annotation)
        assert np.array_equal(mask > 0, roi.mask.data > 0)
        assert annotation["area"] == mask.sum() > 0
        x, y, w, h = annotation["bbox"]
        assert mask[y:y + h, x:x + w].sum() == mask.sum() and x + w <= image["width"]
    manifest = json.loads(archive.read("manifest.json"))
    assert manifest["exported"] == expected.total() and manifest["skipped"] == {}


def test_coco_scene_images_carry_every_cluster_box_and_mask(memory, tmp_path, kitchen_rgb):
    _, archive = exported(memory, format="coco", robot=["synth"], label="detection")
    (tmp_path / "coco.json").write_bytes(archive.read("annotations.json"))
    coco = COCO(str(tmp_path / "coco.json"))
    assert len(coco.imgs) == SYNTH_SCENES and len(coco.anns) == SYNTH_SCENES * SYNTH_CLUSTERS
    for image in coco.imgs.values():
        assert np.array_equal(decoded(archive, f"images/{image['file_name']}"), kitchen_rgb)
        assert len(coco.getAnnIds(imgIds=image["id"])) == SYNTH_CLUSTERS
    for annotation in coco.anns.values():
        cluster = memory.get_cluster(ObjectId(annotation["cluster_id"]))
        (detection,) = [a for a in cluster.annotations if type(a).__name__ == "Detection"]
        assert list(detection.box) == annotation["bbox"]  # synthetic masks fill the box
        assert coco.cats[annotation["category_id"]]["name"] == detection.name
        x, y, w, h = annotation["bbox"]
        mask = coco.annToMask(annotation)
        assert mask[y:y + h, x:x + w].all() and mask.sum() == w * h == annotation["area"]


def test_by_default_coco_takes_scene_images_where_there_are_any_else_crops(memory):
    """The kitchen week's scenes have crops and no camera image; the synthetic ones have one."""
    _, archive = exported(memory, format="coco", robot=["pr2", "synth"])
    coco = json.loads(archive.read("annotations.json"))
    manifest = json.loads(archive.read("manifest.json"))
    week = memory.clusters.count_documents({"search.robot": "pr2"})
    synth = SYNTH_SCENES * SYNTH_CLUSTERS
    assert manifest["images"] == "auto" and manifest["skipped"] == {}
    assert len(coco["annotations"]) == manifest["exported"] == week + synth
    assert len(coco["images"]) == week + SYNTH_SCENES
    assert sorted(n for n in archive.namelist() if n.endswith(".png")) == sorted(
        f"images/{image['file_name']}" for image in coco["images"])


def test_pnp09_has_no_pixels_so_image_formats_skip_it_and_say_why(memory):
    for query in ({"format": "coco"}, {"format": "yolo", "images": "crops"},
                  {"format": "imagefolder"}):
        _, archive = exported(memory, robot=["pnp09"], label="ground_truth", **query)
        manifest = json.loads(archive.read("manifest.json"))
        assert manifest["exported"] == 0 and sum(manifest["skipped"].values()) == 9
        assert not [n for n in archive.namelist() if n.endswith(".png")]


# --- YOLO -----------------------------------------------------------------------------------


@pytest.mark.parametrize("images", ["scenes", "crops"])
def test_yolo_label_files_are_in_range_and_match_their_images(memory, images):
    _, archive = exported(memory, format="yolo", images=images, robot=["synth"])
    names = set(archive.namelist())
    data = yaml.safe_load(archive.read("data.yaml"))
    assert data["nc"] == len(data["names"]) and data["train"] == "images"
    pictures = sorted(n for n in names if n.startswith("images/"))
    assert len(pictures) == (SYNTH_SCENES if images == "scenes" else
                             SYNTH_SCENES * SYNTH_CLUSTERS)
    boxes = 0
    for picture in pictures:
        label_file = "labels/" + Path(picture).with_suffix(".txt").name
        assert label_file in names
        height, width = decoded(archive, picture).shape[:2]
        for line in archive.read(label_file).decode().splitlines():
            cls, cx, cy, w, h = line.split()
            assert 0 <= int(cls) < data["nc"]
            cx, cy, w, h = map(float, (cx, cy, w, h))
            assert 0 < w <= 1 and 0 < h <= 1
            assert -1e-6 <= cx - w / 2 < cx + w / 2 <= 1 + 1e-6
            assert -1e-6 <= cy - h / 2 < cy + h / 2 <= 1 + 1e-6
            if images == "scenes":  # 64 px boxes on the 640x480 frame
                assert (round(w * width), round(h * height)) == (64, 64)
            boxes += 1
    assert boxes == SYNTH_SCENES * SYNTH_CLUSTERS
    assert Counter(data["names"][int(line.split()[0])]
                   for n in names if n.startswith("labels/")
                   for line in archive.read(n).decode().splitlines()) == classified(memory,
                                                                                    "synth")


# --- ImageFolder and JSONL ------------------------------------------------------------------


def test_imagefolder_holds_each_crop_under_its_label_with_provenance(memory):
    _, archive = exported(memory, format="imagefolder", robot=["pr2"], label="object",
                          region=["table"])
    crops = [n for n in archive.namelist() if n.endswith(".png")]
    provenance = {p["file"]: p for p in lines(archive, "provenance.jsonl")}
    assert set(crops) == set(provenance) and crops
    folders = json.loads(archive.read("classes.json"))
    names = {o["_id"]: o["name"] for o in memory.db.objects.find()}
    for name in crops:
        record = provenance[name]
        cluster = memory.get_cluster(ObjectId(record["cluster_id"]))
        scene = memory.scenes.find_one({"_id": cluster.scene_id})
        assert name.split("/")[0] == folders[names[cluster.object_id]]
        assert record["label"] == names[cluster.object_id] and record["annotator"]
        assert record["scene_id"] == str(scene["_id"]) and record["time"] == scene["timestamp"]
        assert record["region"] == cluster.region == "table"
        assert record["camera_pose"]["translation"] == list(scene["camera_pose"]["translation"])
        assert np.array_equal(decoded(archive, name), cluster.hypotheses[0].crop.data)
    on_table = memory.clusters.count_documents({"search.robot": "pr2",
                                                "search.region": "table"})
    assert len(crops) == on_table


def test_jsonl_of_pnp09_has_ground_truth_and_the_raw_features(memory):
    _, archive = exported(memory, format="jsonl", robot=["pnp09"], label="ground_truth")
    rows = lines(archive, "features.jsonl")
    provenance = lines(archive, "provenance.jsonl")
    assert len(rows) == len(provenance) == 9
    with (PNP / "persistent_objects.bson").open("rb") as file:
        raw = list(bson.decode_file_iter(file))
    truth = {}
    for doc in raw:
        for a in doc["annotations"]:
            if a["_type"] == "rs.annotation.GroundTruth":
                truth[a["_id"]] = (a["classificationGT"]["classname"], a["source"])
            if a["_type"] == "rs.pcl.PclFeature":
                vfh = np.frombuffer(a["feature"], "<f4")
        assert any(row["features"].get("VFH") == vfh.astype(float).tolist() for row in rows)
    assert Counter(r["label"] for r in rows) == Counter(name for name, _ in truth.values())
    for row, record in zip(rows, provenance, strict=True):
        assert record["line"] == rows.index(row) + 1 and record["cluster_id"] == row["cluster_id"]
        assert truth[ObjectId(record["annotation_id"])] == (row["label"], record["annotator"])
        assert len(row["features"]["VFH"]) == 308 and len(row["features"]["Caffe"]) == 4096


def test_jsonl_keeps_only_the_features_asked_for(memory):
    _, archive = exported(memory, format="jsonl", robot=["synth"], feature=["VFH"])
    rows = lines(archive, "features.jsonl")
    assert len(rows) == SYNTH_SCENES * SYNTH_CLUSTERS
    assert all(set(r["features"]) == {"VFH"} for r in rows)
    _, none = exported(memory, format="jsonl", robot=["pr2"], feature=["VFH"], limit=20)
    assert json.loads(none.read("manifest.json"))["skipped"] == {
        "no feature vector named VFH": memory.clusters.count_documents({"search.robot": "pr2"})}


# --- determinism, streaming, label sources --------------------------------------------------


def test_the_same_store_and_query_give_the_same_bytes(memory):
    first, archive = exported(memory, format="coco", images="crops", robot=["pr2"], limit=300)
    again, _ = exported(memory, format="coco", images="crops", robot=["pr2"], limit=300)
    assert first == again
    assert {info.date_time for info in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    assert archive.testzip() is None


def test_the_zip_streams_as_it_is_written(memory):
    chunks = list(Export(memory, ExportQuery(format="imagefolder", robot=["pr2"],
                                             limit=400)).zip_stream())
    archive = zipfile.ZipFile(io.BytesIO(b"".join(chunks)))
    scenes = {p["scene_id"] for p in lines(archive, "provenance.jsonl")}
    assert len(chunks) >= len(scenes) > 50  # handed on scene by scene, as written
    assert max(map(len, chunks)) <= 2**20


def test_clusters_without_a_label_from_the_source_are_skipped_and_counted(memory):
    """A limit counts the clusters exported: with none labelled, every selected one is
    skipped (and said so), not just the first `limit`."""
    _, archive = exported(memory, format="jsonl", robot=["pr2"], label="detection", limit=50)
    manifest = json.loads(archive.read("manifest.json"))
    assert manifest["exported"] == 0 and manifest["skipped"] == {
        "no detection label": memory.clusters.count_documents({"search.robot": "pr2"})}
    _, by_text = exported(memory, format="jsonl", robot=["pr2"], label="text", limit=50)
    texts = lines(by_text, "provenance.jsonl")
    assert texts and all(p["annotator"] == "OCRAnnotator" for p in texts)


def test_the_limit_takes_the_oldest(memory):
    _, archive = exported(memory, format="jsonl", robot=["pr2"], limit=10)
    times = [p["time"] for p in lines(archive, "provenance.jsonl")]
    oldest = [d["search"]["time"] for d in memory.clusters.find({"search.robot": "pr2"}).sort(
        [("search.time", 1), ("_id", 1)]).limit(10)]
    assert times == oldest


def test_the_limit_counts_the_clusters_exported_not_those_skipped(memory):
    """The oldest selected clusters have no label from this source: a limit of 10 still
    exports the 10 oldest that have one."""
    labelled = [d["_id"] for d in memory.clusters.find(
        {"search.robot": "pr2", "annotations._type": "pm.annotation.Text"}).sort(
        [("search.time", 1), ("_id", 1)]).limit(10)]
    first = memory.clusters.find({"search.robot": "pr2"}).sort(
        [("search.time", 1), ("_id", 1)]).limit(20)
    assert len(labelled) == 10 and any(d["_id"] not in labelled for d in first)
    _, archive = exported(memory, format="jsonl", robot=["pr2"], label="text", limit=10)
    rows = lines(archive, "provenance.jsonl")
    assert [ObjectId(p["cluster_id"]) for p in rows] == labelled
    assert json.loads(archive.read("manifest.json"))["exported"] == 10


# --- HTTP API and CLI -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def client(memory):
    return TestClient(create_app(memory, Settings()), base_url=LOCAL)


def test_the_api_streams_the_same_zip_by_get_and_post(client, memory):
    by_get = client.get("/api/export", params={"format": "yolo", "robot": "synth",
                                               "images": "crops"})
    by_post = client.post("/api/export", json={"format": "yolo", "robot": ["synth"],
                                               "images": "crops"})
    assert by_get.status_code == by_post.status_code == 200
    assert by_get.headers["content-type"] == "application/zip"
    assert by_get.content == by_post.content == exported(
        memory, format="yolo", robot=["synth"], images="crops")[0]


@pytest.mark.parametrize(("params", "problem"), [
    ({"format": "xml"}, "format"),
    ({"format": "coco", "feature": "VFH"}, "feature"),
    ({"format": "jsonl", "images": "crops"}, "images"),
    ({"format": "coco", "label": "colour"}, "label"),
    ({"format": "coco", "limit": "0"}, "limit"),
    ({"format": "coco", "robto": "pr2"}, "robto"),
])
def test_bad_export_queries_get_422_naming_the_problem(client, params, problem):
    answer = client.get("/api/export", params=params)
    assert answer.status_code == 422
    assert problem in json.dumps(answer.json()["error"])


def test_an_export_with_nothing_in_it_is_a_422_naming_why(client):
    answer = client.get("/api/export", params={"format": "coco", "robot": "pnp09"})
    assert answer.status_code == 422
    assert answer.json()["error"]["message"] == (
        "nothing exported: every selected cluster was skipped: 9 (no classification label)")
    answer = client.post("/api/export", json={"format": "coco", "robot": ["nobody"]})
    assert answer.status_code == 422
    assert answer.json()["error"]["message"] == "nothing exported: the query selects no clusters"


def test_the_search_pages_download_is_a_zip_with_annotations(client):
    """The search form's export with its defaults (format coco, images and label as given)."""
    answer = client.get("/api/export", params={"text": "cereal", "format": "coco",
                                               "images": "", "label": "object"})
    assert answer.status_code == 200
    coco = json.loads(zipfile.ZipFile(io.BytesIO(answer.content)).read("annotations.json"))
    assert coco["annotations"] and len(coco["images"]) == len(coco["annotations"])


def test_a_query_that_cannot_run_is_refused_before_streaming(client):
    answer = client.post("/api/export", json={"format": "coco", "text": "!!"})
    assert answer.status_code == 422 and "no words" in answer.json()["error"]["message"]


def test_pmem_export_writes_a_zip_or_a_folder(memory, mongo_uri, db_name, tmp_path):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    run = CliRunner().invoke(main, ["export", "jsonl", "--robot", "pnp09", "--label",
                                    "ground_truth", "--out", str(tmp_path / "pnp.zip")], env=env)
    assert run.exit_code == 0, run.output
    assert "exported 9 clusters" in run.output
    assert (tmp_path / "pnp.zip").read_bytes() == exported(
        memory, format="jsonl", robot=["pnp09"], label="ground_truth")[0]
    folder = tmp_path / "crops"
    run = CliRunner().invoke(main, ["export", "imagefolder", "--robot", "synth",
                                    "--out", str(folder)], env=env)
    assert run.exit_code == 0, run.output
    assert len(list(folder.glob("*/*.png"))) == SYNTH_SCENES * SYNTH_CLUSTERS
    again = CliRunner().invoke(main, ["export", "imagefolder", "--out", str(folder)], env=env)
    assert again.exit_code == 1 and "not an empty folder" in again.output


@pytest.mark.parametrize("name", ["stopped.zip", "stopped"])
def test_an_export_stopped_midway_leaves_nothing_and_no_traceback(memory, tmp_path, name):
    """Ctrl-C in the middle: nothing at the path nor beside it, and zipfile does not write
    the end of the zip onto the closed file when collected (it printed a traceback)."""
    unraisable = []
    hook, sys.unraisablehook = sys.unraisablehook, unraisable.append
    try:
        export = Export(memory, ExportQuery(format="coco", images="crops"))

        def stop(done):
            raise KeyboardInterrupt
        with pytest.raises(KeyboardInterrupt):
            export.save(tmp_path / name, stop)
        del export
        gc.collect()
    finally:
        sys.unraisablehook = hook
    assert not unraisable
    assert not list(tmp_path.iterdir())


def test_pmem_export_stopped_by_sigterm_leaves_nothing(memory, mongo_uri, db_name, tmp_path):
    """A scheduler's SIGTERM killed the export where it was: a zip that was no zip, a folder
    without its manifest, at the path asked for. Now it is stopped as by Ctrl-C."""
    script = (
        "import os, signal, sys\n"
        "from percept_memory.cli import main\n"
        "from percept_memory.queries.export import run\n"
        "write = run.Export.write\n"
        "def stopped(self, archive):\n"
        "    for n, done in enumerate(write(self, archive)):\n"
        "        if n == 2:\n"
        "            os.kill(os.getpid(), signal.SIGTERM)\n"
        "        yield done\n"
        "run.Export.write = stopped\n"
        "main(sys.argv[1:])\n")
    for out in (tmp_path / "term.zip", tmp_path / "term"):
        ran = subprocess.run([sys.executable, "-c", script, "export", "coco", "--images",
                              "crops", "--out", str(out)], capture_output=True, text=True,
                             env={**os.environ, "MONGODB_URI": mongo_uri, "PMEM_DB": db_name},
                             timeout=120)
        assert ran.returncode == 1, ran.stderr
        assert "Traceback" not in ran.stderr and "Exception ignored" not in ran.stderr
        assert not list(tmp_path.iterdir())


def test_pmem_export_of_nothing_fails_and_says_why(memory, mongo_uri, db_name, tmp_path):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    run = CliRunner().invoke(main, ["export", "coco", "--robot", "pnp09",
                                    "--out", str(tmp_path / "pnp.zip")], env=env)
    assert run.exit_code == 1 and not (tmp_path / "pnp.zip").exists()
    assert "Error: nothing exported: every selected cluster was skipped: 9 (no classification " \
           "label)" in run.output
    run = CliRunner().invoke(main, ["export", "imagefolder", "--robot", "pnp09",
                                    "--out", str(tmp_path / "pnp")], env=env)
    assert run.exit_code == 1 and not (tmp_path / "pnp").exists()
    run = CliRunner().invoke(main, ["export", "coco", "--robot", "nobody",
                                    "--out", str(tmp_path / "none.zip")], env=env)
    assert run.exit_code == 1 and not (tmp_path / "none.zip").exists()
    assert "Error: nothing exported: the query selects no clusters" in run.output


def test_names_become_paths_every_file_system_and_unzip_take(store, kitchen_rgb):
    """Image names and labels are names (one line, at most 200 characters) but not file
    names: an image named rgb.png was left out ('no image the box is in'), one with .. in it
    failed every export (500), and labels made folders unzip could not create."""
    rng = np.random.default_rng(11)
    labels = ["Cup", "cup", "CON", "é" * 200, "😀 mug", "x" * 100, "X" * 100]
    images = ["rgb.png", "../../x/CON", "depth/../color", "RGB.png"]
    scenes = []
    for i, image in enumerate(images):
        scene = synthetic.scene(rng, 1_700_000_000_000_000_000 + i, len(labels), kitchen_rgb,
                                robot="odd")
        scene.images = {image: Image(data=kitchen_rgb, encoding="bgr8")}
        for cluster, label in zip(scene.clusters, labels, strict=True):
            cluster.hypotheses[0].image = image
            for said in cluster.annotations_of(Classification):
                said.class_name = label
        scenes.append(scene)
    list(IngestService(store).ingest_stream((str(i), s) for i, s in enumerate(scenes)))
    for kind in ("coco", "yolo", "imagefolder"):
        _, archive = exported(store, format=kind, robot=["odd"],
                              **({} if kind == "imagefolder" else {"images": "scenes"}))
        names = archive.namelist()
        assert all(part not in ("", ".", "..") and len(part.encode()) < 255
                   for n in names for part in n.split("/")), names
        assert len({n.casefold() for n in names}) == len(names), names
        summary = json.loads(archive.read("manifest.json"))
        assert summary["exported"] == len(labels) * len(images), (kind, summary)
        if kind == "coco":
            pictures = [n for n in names if n.startswith("images/")]
            assert len(pictures) == len(images) and all(n.count("/") == 1 for n in pictures)
        if kind == "yolo":
            assert "😀 mug" in yaml.safe_load(archive.read("data.yaml"))["names"].values()
        if kind == "imagefolder":
            folders = json.loads(archive.read("classes.json"))
            assert len({f.casefold() for f in folders.values()}) == len(labels)
            assert folders["CON"] == "_CON" and len(folders["é" * 200]) <= 60
            assert all(len(folder) <= 60 for folder in folders.values())
