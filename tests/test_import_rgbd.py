"""The RGB-D samples importer on RoboSherlock's real samples: the kitchen frame (RGB + depth +
viewpoint) and low_noise (RGB + PCD + ground-truth segments)."""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import cv2
import imagehash
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image as PILImage
from scipy.spatial.transform import Rotation

from percept_memory.cli import main
from percept_memory.ingest.rgbd import SampleError, read_pcd, read_samples
from percept_memory.ingest.scene_log import read_scene_log, write_scene_log
from percept_memory.ingest.service import IngestService
from percept_memory.memory.errors import SceneExists
from percept_memory.memory.types import (
    ColorHistogram,
    Geometry,
    ImageROI,
    LogLine,
    PointCluster,
    Scene,
)
from tests.conftest import ROBOSHERLOCK
from tests.test_cli import error_line

SAMPLES = ROBOSHERLOCK / "samples"
KITCHEN = SAMPLES / "kitchen"
LOW_NOISE = SAMPLES / "low_noise"
STAMP = "1522249987296654516"
OUTPUT = Path(__file__).resolve().parents[1] / "test-output"
K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])

# What is on the kitchen counter, as pixels of the RGB image. Bowl, plate and spoon touch and
# are one cluster; the glass is transparent (only its rim has depth); the flat plastic knife is
# within the Kinect's depth noise of the counter, so segmentation cannot see it.
JUICE, MUESLI, BOWL, GLASS = (268, 130), (338, 150), (330, 240), (435, 180)
CABINET = (60, 100)  # the tall cabinet's side at the counter's left edge: not an object
COUNTER = (slice(300, 340), slice(520, 560))  # bare counter, rows and columns


@pytest.fixture(scope="module")
def kitchen() -> Scene:
    (scene,) = read_samples(KITCHEN)
    return scene


@pytest.fixture(scope="module")
def low_noise() -> list[Scene]:
    return list(read_samples(LOW_NOISE))


def roi(cluster) -> ImageROI:
    return cluster.hypothesis_of(ImageROI)


def covers(box, pixel) -> bool:
    x, y, w, h = box
    return x <= pixel[0] < x + w and y <= pixel[1] < y + h


def ground_truth(path: Path) -> list[np.ndarray]:
    """The .lbl segments, read here independently of the importer."""
    lines = path.read_text().splitlines()
    segments, index = [], 1
    while index < len(lines):
        if lines[index].startswith("---"):
            segments.append([])
            index += 3
            continue
        if lines[index].strip():
            segments[-1].append(int(lines[index]))
        index += 1
    assert len(segments) == int(lines[0].split()[0])
    return [np.array(s) for s in segments]


# --- kitchen: RGB + depth + viewpoint -----------------------------------------------------------


def test_kitchen_finds_the_objects_on_the_counter(kitchen):
    boxes = [roi(c).box for c in kitchen.clusters]
    assert 4 <= len(boxes) <= 7
    for name, pixel in {"juice": JUICE, "muesli": MUESLI, "bowl": BOWL, "glass": GLASS}.items():
        assert any(covers(box, pixel) for box in boxes), name
    assert not any(covers(box, CABINET) for box in boxes)
    assert {c.region for c in kitchen.clusters} == {"counter_top"}
    assert kitchen.timestamp == int(STAMP) and kitchen.frame == "map"
    assert kitchen.camera_pose.child_frame == "head_mount_kinect_rgb_optical_frame"
    assert kitchen.images["color"].encoding == "bgr8"
    assert kitchen.images["depth"].encoding == "mono16"
    assert kitchen.images["depth"].data.dtype == np.uint16


def test_kitchen_centroids_are_above_the_counter_and_in_view(kitchen):
    depth = kitchen.images["depth"].data
    to_map = kitchen.camera_pose.matrix()
    rows, columns = np.mgrid[COUNTER]
    z = depth[COUNTER] / 1000.0
    ok = z > 0
    camera = np.stack([(columns[ok] - 319.5) * z[ok] / 525, (rows[ok] - 239.5) * z[ok] / 525,
                       z[ok]], axis=1)
    counter_height = np.median((camera @ to_map[:3, :3].T + to_map[:3, 3])[:, 2])
    assert 0.75 < counter_height < 0.9
    to_camera = np.linalg.inv(to_map)
    for cluster in kitchen.clusters:
        position = np.array(cluster.position)
        assert position[2] > counter_height + 0.01
        assert cluster.annotations_of(Geometry)[0].distance_to_plane > 0
        seen = to_camera[:3, :3] @ position + to_camera[:3, 3]
        u, v = (K @ seen)[:2] / seen[2]
        assert seen[2] > 0 and 0 <= u < 640 and 0 <= v < 480
        assert covers(roi(cluster).box, (u, v))
        points = cluster.hypothesis_of(PointCluster).points
        assert points.frame == "map"
        assert np.allclose(points.xyz().mean(axis=0), position, atol=1e-3)


def test_kitchen_imports_fast_and_logs_its_steps(kitchen):
    start = time.perf_counter()
    list(read_samples(KITCHEN))
    assert time.perf_counter() - start < 5.0
    for step in ("plane fit", "Euclidean clustering"):
        assert any(line.message.startswith(step) for line in kitchen.log), step
    assert all(isinstance(line, LogLine) and line.source == "RGBDImporter"
               and line.duration_ms >= 0 for line in kitchen.log)


def test_kitchen_debug_image(kitchen):
    """Boxes and masks drawn on the frame, to look at: test-output/rgbd_kitchen.png."""
    image = kitchen.images["color"].data.copy()
    for number, cluster in enumerate(kitchen.clusters):
        x, y, w, h = roi(cluster).box
        inside = image[y:y + h, x:x + w]
        inside[roi(cluster).mask.data > 0] = inside[roi(cluster).mask.data > 0] // 2 + (0, 0, 127)
        cv2.rectangle(image, (x, y), (x + w - 1, y + h - 1), (0, 0, 255), 2)
        cv2.putText(image, str(number), (x + 3, y + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (0, 0, 255), 2)
    OUTPUT.mkdir(exist_ok=True)
    assert cv2.imwrite(str(OUTPUT / "rgbd_kitchen.png"), image)


# --- low_noise: RGB + PCD + ground truth --------------------------------------------------------


def test_low_noise_clusters_are_the_ground_truth_segments(low_noise):
    # The clouds are cut to the objects: no segment is the table, so none is skipped.
    expected = {"ground_truth.lbl": 9, "ground_truth1.lbl": 8}
    for scene, (labels, count) in zip(low_noise, expected.items(), strict=True):
        segments = ground_truth(LOW_NOISE / labels)
        assert len(scene.clusters) == len(segments) == count
        for cluster, segment in zip(scene.clusters, segments, strict=True):
            hypothesis = cluster.hypothesis_of(PointCluster)
            assert hypothesis.cloud == "cloud"
            assert np.array_equal(hypothesis.indices, segment)
            centroid = scene.clouds["cloud"].xyz()[segment].mean(axis=0)
            assert np.allclose(cluster.position, centroid)
            assert cluster.location().frame == "cloud" and cluster.region == "table"


def test_low_noise_keeps_the_cloud_and_is_at_its_files_times(low_noise):
    cloud = low_noise[0].clouds["cloud"]
    assert cloud.points.dtype.names == ("x", "y", "z", "rgb", "normal_x", "normal_y",
                                        "normal_z", "curvature")
    assert len(cloud.points) == 64641 and cloud.frame == "cloud"
    again = list(read_samples(LOW_NOISE))
    assert [s.timestamp for s in again] == [s.timestamp for s in low_noise]
    assert [s.timestamp for s in low_noise] == [
        (LOW_NOISE / name).stat().st_mtime_ns for name in ("cloud.pcd", "cloud1.pcd")]


def test_low_noise_cloud_is_registered_to_the_image(low_noise):
    """Projected from the estimated camera pose, the cloud's colours are those of the image
    under them (occluded points included); from the identity pose (the PCD's VIEWPOINT) they
    are not."""
    for scene in low_noise:
        assert any("registered" in line.message for line in scene.log)
        cloud = scene.clouds["cloud"]
        packed = np.ascontiguousarray(cloud.points["rgb"]).view(np.uint32)
        colours = np.stack([packed & 255, (packed >> 8) & 255, (packed >> 16) & 255], axis=1)
        for pose, low, high in ((scene.camera_pose.matrix(), 0.6, 1.0), (np.eye(4), -1, 0.3)):
            to_camera = np.linalg.inv(pose)
            seen = cloud.xyz() @ to_camera[:3, :3].T + to_camera[:3, 3]
            u, v = np.round((seen @ K.T)[:, :2] / seen[:, 2:]).astype(int).T
            inside = (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
            pixels = scene.images["color"].data[v[inside], u[inside]]
            for channel in range(3):
                r = np.corrcoef(pixels[:, channel], colours[inside, channel])[0, 1]
                assert low < r <= high


def test_without_labels_the_cloud_is_clustered(tmp_path):
    """low_noise's cloud has no table: no plane is taken for one, and the touching objects
    form one Euclidean cluster."""
    for name in ("cloud.pcd", "image.png"):
        shutil.copy(LOW_NOISE / name, tmp_path / name)
    (scene,) = read_samples(tmp_path)
    assert any("no supporting plane" in line.message for line in scene.log)
    indices = np.concatenate([c.hypothesis_of(PointCluster).indices for c in scene.clusters])
    assert len(scene.clusters) in range(1, 10)
    assert len(np.unique(indices)) == len(indices) and indices.max() < 64641


def test_unregistrable_image_falls_back_to_the_pcd_viewpoint(tmp_path):
    shutil.copy(LOW_NOISE / "cloud.pcd", tmp_path / "cloud.pcd")
    cv2.imwrite(str(tmp_path / "image.png"), np.zeros((480, 640, 3), np.uint8))
    (scene,) = read_samples(tmp_path)
    assert [line.level for line in scene.log if "register" in line.message] == ["warning"]
    assert np.allclose(scene.camera_pose.matrix(), np.eye(4))


# --- every cluster, every scene -----------------------------------------------------------------


def test_crops_masks_hashes_and_histograms(kitchen, low_noise):
    for scene in [kitchen, *low_noise]:
        image = scene.images["color"].data
        for cluster in scene.clusters:
            hypothesis = roi(cluster)
            x, y, w, h = hypothesis.box
            crop, mask = hypothesis.crop.data, hypothesis.mask.data
            assert crop.shape == (h, w, 3) and crop.dtype == np.uint8
            assert np.array_equal(crop, image[y:y + h, x:x + w])
            assert mask.shape == (h, w) and set(np.unique(mask)) <= {0, 255} and mask.any()
            assert hypothesis.mask.encoding == "mono8" and hypothesis.crop.encoding == "bgr8"
            ok, png = cv2.imencode(".png", crop)
            assert ok and cv2.imdecode(png, cv2.IMREAD_COLOR).shape == crop.shape
            assert re.fullmatch(r"[0-9a-f]{16}", hypothesis.phash)
            rgb = PILImage.fromarray(cv2.cvtColor(crop, cv2.COLOR_BGR2RGB))
            assert hypothesis.phash == str(imagehash.phash(rgb))
            (histogram,) = cluster.annotations_of(ColorHistogram)
            assert histogram.histogram.shape == (16, 16)
            assert histogram.histogram.dtype == np.float32
            assert histogram.histogram.sum() == pytest.approx(1.0, abs=1e-5)
            assert all(s > 0 for s in cluster.annotations_of(Geometry)[0].size)


# --- storing ------------------------------------------------------------------------------------


def same_array(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_stored_bit_exact_and_imported_once(store, kitchen, low_noise):
    service = IngestService(store)
    scenes = [kitchen, *low_noise]
    ids = [landed.ids for landed in service.ingest_stream(enumerate(scenes))]
    assert all(i.created for i in ids)
    counts = store.counts()
    for scene, stored_ids in zip(scenes, ids, strict=True):
        stored = store.get_scene(stored_ids.scene_id)
        for name, image in scene.images.items():
            assert same_array(stored.images[name].data, image.data), name
        for name, cloud in scene.clouds.items():
            assert same_array(stored.clouds[name].points, cloud.points), name
        assert len(stored.clusters) == len(scene.clusters)
        for mine, theirs in zip(scene.clusters, stored.clusters, strict=True):
            assert same_array(roi(theirs).crop.data, roi(mine).crop.data)
            assert same_array(roi(theirs).mask.data, roi(mine).mask.data)
            assert roi(theirs).phash == roi(mine).phash

    again = [landed.ids for landed in service.ingest_stream(enumerate(
        [*read_samples(KITCHEN), *read_samples(LOW_NOISE)]))]
    assert [i.scene_id for i in again] == [i.scene_id for i in ids]
    assert not any(i.created for i in again)
    assert store.counts() == counts
    # read from their parent folder, the same files are scenes of another map (the folder's
    # name): not the scenes stored, refused by name rather than acknowledged and dropped
    with pytest.raises(SceneExists, match="'pr2' has another scene stored"):
        list(service.ingest_stream(enumerate(read_samples(SAMPLES))))
    assert store.counts() == counts


def test_a_structured_cloud_written_as_a_scene_log_reads_back_exactly(low_noise, tmp_path):
    """The cloud's x, y, z, rgb fields travel in the array's dtype, as numpy describes it."""
    write_scene_log(low_noise, tmp_path)
    first = json.loads((tmp_path / "scenes.jsonl").read_text().splitlines()[0])
    assert [field[0] for field in first["clouds"]["cloud"]["points"]["dtype"]][:3] == \
        ["x", "y", "z"]
    back = [Scene.model_validate(data, context={"folder": tmp_path})
            for _, data in read_scene_log(tmp_path)]
    for scene, read in zip(low_noise, back, strict=True):
        assert same_array(read.clouds["cloud"].points, scene.clouds["cloud"].points)
        assert read == scene


# --- bad files ----------------------------------------------------------------------------------


def kitchen_copy(folder: Path) -> None:
    for name in (f"rgb_{STAMP}.png", f"depth_{STAMP}.png", f"viewpoint_{STAMP}.vp"):
        shutil.copy(KITCHEN / name, folder / name)


def cloud_copy(folder: Path, data: bytes) -> None:
    shutil.copy(LOW_NOISE / "image.png", folder / "image.png")
    (folder / "cloud.pcd").write_bytes(data)


def test_truncated_pcd(tmp_path):
    raw = (LOW_NOISE / "cloud.pcd").read_bytes()
    cloud_copy(tmp_path, raw[: len(raw) // 2])
    with pytest.raises(SampleError, match=r"cloud\.pcd: truncated: 64641 points"):
        list(read_samples(tmp_path))


def test_binary_compressed_pcd(tmp_path):
    raw = (LOW_NOISE / "cloud.pcd").read_bytes()
    cloud_copy(tmp_path, raw.replace(b"DATA binary\n", b"DATA binary_compressed\n", 1))
    with pytest.raises(SampleError, match=r"cloud\.pcd: DATA binary_compressed is not supp"):
        list(read_samples(tmp_path))


def test_depth_that_is_not_16_bit(tmp_path):
    kitchen_copy(tmp_path)
    cv2.imwrite(str(tmp_path / f"depth_{STAMP}.png"), np.zeros((480, 640), np.uint8))
    with pytest.raises(SampleError, match=rf"depth_{STAMP}\.png: depth must be a 16-bit .*"
                                          r"got 8-bit"):
        list(read_samples(tmp_path))


def test_viewpoint_missing_a_key(tmp_path):
    kitchen_copy(tmp_path)
    vp = tmp_path / f"viewpoint_{STAMP}.vp"
    vp.write_text(re.sub(r"(?m)^w=.*\n", "", vp.read_text()))
    with pytest.raises(SampleError, match=rf"viewpoint_{STAMP}\.vp: missing key 'w' in "
                                          r"section \[rotation\]"):
        list(read_samples(tmp_path))


def test_a_viewpoint_of_no_rotation_is_one_line_naming_the_field(tmp_path):
    kitchen_copy(tmp_path)
    vp = tmp_path / f"viewpoint_{STAMP}.vp"
    vp.write_text(re.sub(r"(?m)^([xyzw])=.*$", r"\1=0", vp.read_text().split("[frame]")[0])
                  + "[frame]" + vp.read_text().split("[frame]")[1])
    with pytest.raises(SampleError) as raised:
        list(read_samples(tmp_path))
    message = str(raised.value)
    assert f"viewpoint_{STAMP}.vp: bad value: rotation: " in message
    assert "\n" not in message and "errors.pydantic.dev" not in message


def test_ascii_pcd_reads_like_binary(tmp_path):
    binary, viewpoint = read_pcd(LOW_NOISE / "cloud.pcd")
    head = binary[:50]
    names = head.dtype.names
    rows = [" ".join(np.format_float_scientific(point[n], unique=True) for n in names)
            for point in head]
    header = ("VERSION 0.7\nFIELDS " + " ".join(names) + "\nSIZE" + " 4" * len(names)
              + "\nTYPE" + " F" * len(names) + "\nCOUNT" + " 1" * len(names)
              + "\nWIDTH 50\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 50\nDATA ascii\n")
    path = tmp_path / "ascii.pcd"
    path.write_text(header + "\n".join(rows) + "\n")
    ascii_cloud, ascii_viewpoint = read_pcd(path)
    assert same_array(ascii_cloud, head)
    assert np.array_equal(ascii_viewpoint, viewpoint)


# --- the command: times, layouts, image sizes ---------------------------------------------------


def pmem_import(folder: Path, mongo_uri: str, db_name: str, *options: str):
    return CliRunner().invoke(main, ["import", "rgbd", str(folder), *options],
                              env={"MONGODB_URI": mongo_uri, "PMEM_DB": db_name})


def test_a_folder_without_samples_fails_naming_the_layouts(tmp_path, mongo_uri, db_name):
    (tmp_path / "notes.txt").write_text("no samples here")
    result = pmem_import(tmp_path, mongo_uri, db_name)
    assert result.exit_code == 1
    assert f"Error: no RGB-D samples in {tmp_path}: looked for rgb_<stamp>.png + " \
           "depth_<stamp>.png + viewpoint_<stamp>.vp, cloud<n>.pcd + image<n>.png" in result.stderr
    assert "test_point_cloud_<n>.pcd + test_rgb_image_<n>.png + test_viewpoint_<n>.vp" \
        in result.stderr


def test_samples_recording_no_time_are_at_the_time_given(store, tmp_path, mongo_uri, db_name):
    for name in ("cloud.pcd", "image.png", "ground_truth.lbl"):
        shutil.copy(LOW_NOISE / name, tmp_path / name)
    result = pmem_import(tmp_path, mongo_uri, db_name, "--time", "2018-03-28T15:13:07Z",
                         "--map", "given")
    assert result.exit_code == 0, result.output
    assert "1 new scene" in result.stdout
    assert "scene times: 1 from the time given, a second apart" in result.stdout
    (scene,) = store.scenes.find({"map": "given"})
    assert scene["timestamp"] == 1522249987 * 10**9
    objects = list(store.db.objects.find({"map": "given"}))
    assert len(objects) == 9 and all(o["first_seen"] == o["last_seen"] for o in objects)
    bad = pmem_import(tmp_path, mongo_uri, db_name, "--time", "yesterday")
    assert "expected an ISO 8601 time" in error_line(bad)


def test_robosherlocks_test_sample_at_twice_the_kinects_resolution(store, tmp_path, mongo_uri,
                                                                   db_name, low_noise):
    """RoboSherlock's test_rgb_image_01.png (1280x960) + test_point_cloud_01.pcd +
    test_viewpoint_01.vp, made from low_noise's first sample: the intrinsics are scaled to the
    image, the camera is found where it is at 640x480, the time is the viewpoint's stamp."""
    image = cv2.imread(str(LOW_NOISE / "image.png"))
    cv2.imwrite(str(tmp_path / "test_rgb_image_01.png"),
                cv2.resize(image, (1280, 960), interpolation=cv2.INTER_CUBIC))
    shutil.copy(LOW_NOISE / "cloud.pcd", tmp_path / "test_point_cloud_01.pcd")
    shutil.copy(KITCHEN / f"viewpoint_{STAMP}.vp", tmp_path / "test_viewpoint_01.vp")
    result = pmem_import(tmp_path, mongo_uri, db_name, "--map", "test sample", "--robot",
                         "tester")  # the kitchen's viewpoint: its time, another robot
    assert result.exit_code == 0, result.output
    assert "1 new scene" in result.stdout
    assert "scene times: 1 from the stamps of the viewpoint files" in result.stdout
    (doc,) = store.scenes.find({"map": "test sample"}, {"_id": 1})
    scene = store.get_scene(doc["_id"])
    assert scene.timestamp == int(STAMP)
    assert (scene.camera.width, scene.camera.height) == (1280, 960)
    assert scene.camera.k == (1050.0, 0.0, 639.5, 0.0, 1050.0, 479.5, 0.0, 0.0, 1.0)
    assert any(line.message.startswith("registered") for line in scene.log)
    found, there = scene.camera_pose, low_noise[0].camera_pose
    assert np.linalg.norm(np.subtract(found.translation, there.translation)) < 0.05
    turn = Rotation.from_quat(found.rotation).inv() * Rotation.from_quat(there.rotation)
    assert np.degrees(turn.magnitude()) < 2
    for cluster in scene.clusters:
        x, y, w, h = roi(cluster).box
        assert x + w <= 1280 and y + h <= 960 and w > 100
