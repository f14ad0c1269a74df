"""The generated kitchen week: deterministic, consistent with its own ground truth, realistic
enough (stable appearance per object, distinct across objects) and storable."""

from __future__ import annotations

import itertools
from collections import Counter
from datetime import timedelta

import numpy as np
import pytest

from percept_memory.demo import kitchen_week as kw
from percept_memory.ingest.service import IngestService
from percept_memory.memory.types import (
    Classification,
    Location,
    Logo,
    Product,
    Text,
    datetime_from_timestamp,
)

DAY = 86_400 * kw.SECOND


@pytest.fixture(scope="module")
def week() -> kw.KitchenWeek:
    return kw.generate()


def crops(week: kw.KitchenWeek) -> list[bytes]:
    return [c.hypotheses[0].crop.data.tobytes() for s in week.scenes for c in s.clusters]


# --- determinism ----------------------------------------------------------------------------


def test_the_same_seed_gives_the_same_week_bit_for_bit(week):
    again = kw.generate()
    assert [s.timestamp for s in again.scenes] == [s.timestamp for s in week.scenes]
    assert crops(again) == crops(week)
    assert again.scenes == week.scenes  # every value; arrays compared byte for byte
    assert again.truth.actions == week.truth.actions
    assert again.truth.observations == week.truth.observations


def test_another_seed_gives_another_week(week):
    other = kw.generate(seed=1)
    assert [s.timestamp for s in other.scenes] != [s.timestamp for s in week.scenes]
    assert other.truth.actions != week.truth.actions
    assert crops(other)[:50] != crops(week)[:50]


def test_a_shorter_or_later_week_starts_the_same(week):
    monday = kw.generate(days=1, start=kw.START + timedelta(days=7))
    first_day = [s for s in week.scenes if s.timestamp < week.scenes[0].timestamp + DAY]
    assert len(monday.scenes) == len(first_day)
    for later, scene in zip(monday.scenes, first_day, strict=True):
        assert later.timestamp - scene.timestamp == 7 * DAY
        assert later.clusters == scene.clusters


# --- what the week holds --------------------------------------------------------------------


def test_several_hundred_scenes_over_seven_days(week):
    times = [s.timestamp for s in week.scenes]
    assert 200 <= len(week.scenes) <= 350
    assert times == sorted(times)
    start = datetime_from_timestamp(times[0])
    assert start.date() == kw.START.date()
    assert (datetime_from_timestamp(times[-1]) - kw.START).days == 6
    rounds_per_day = Counter(datetime_from_timestamp(s.time).date()
                             for s in week.truth.scenes if s.region == kw.ROUTE[0])
    assert len(rounds_per_day) == 7 and all(6 <= n <= 10 for n in rounds_per_day.values())
    assert {s.region for s in week.truth.scenes} == set(kw.REGIONS)
    assert all(s.robot == "pr2" and s.camera == kw.KINECT for s in week.scenes)


def test_objects_actions_and_events(week):
    truth = week.truth
    assert len(truth.objects) >= 12
    assert {"cup#1", "cup#2", "cup#3"} <= set(truth.objects)
    assert kw.item_of("cup#1") is kw.item_of("cup#2") is kw.item_of("cup#3")  # identical
    kinds = Counter(a.kind for a in truth.actions)
    assert set(kinds) == {"put", "move", "take", "bring_back", "turn"}
    assert any(a.from_region == a.to_region for a in truth.actions if a.kind == "move")
    water = [a.kind for a in truth.actions if a.object == "water#1"]
    assert "take" in water and water.index("bring_back") > water.index("take")
    pringles = [a for a in truth.actions if a.object.startswith("pringles#")]
    binned = next(a for a in pringles if a.kind == "take")
    assert binned.object == "pringles#1"
    assert all(a.time <= binned.time for a in pringles if a.object == "pringles#1")
    assert any(a.kind == "put" and a.time > binned.time for a in pringles)
    events = Counter(o.event for o in truth.observations)
    assert set(events) == {"appear", "stay", "move", "newview"}
    assert events["appear"] == len(truth.objects)  # the first sight of each
    assert sum(len(s.gone) for s in truth.scenes) > 0
    assert any(not s.objects for s in truth.scenes)  # surfaces seen empty
    quiet = [a for a, b in itertools.pairwise(truth.scenes[:: len(kw.ROUTE)])
             if not truth.actions_between(a.time, b.time)]
    assert quiet  # rounds with nothing done since the last one


def test_annotations_are_those_of_a_perception_pipeline(week):
    clusters = [c for s in week.scenes for c in s.clusters]
    observations = week.truth.observations
    classes = [c.annotations_of(Classification)[0] for c in clusters]
    right = [cls.class_name == kw.item_of(o.object).class_name
             for cls, o in zip(classes, observations, strict=True)]
    assert 0.9 < np.mean(right) < 1.0  # sometimes wrong, then unsure
    assert all(cls.confidence < 0.5 for cls, ok in zip(classes, right, strict=True) if not ok)
    assert all(set(cls.confidences) == set(kw.CLASSES) for cls in classes)
    texts = Counter()
    for cluster, observation in zip(clusters, observations, strict=True):
        item = kw.item_of(observation.object)
        printed = item.front if observation.face == "front" else item.back
        for text in cluster.annotations_of(Text):
            texts["read" if text.text == " ".join(printed) else "misread"] += 1
        assert all(logo.brand == item.brand for logo in cluster.annotations_of(Logo))
        products = cluster.annotations_of(Product)
        assert all(p.name == item.name and p.properties == item.properties for p in products)
        if not item.brand:
            assert not cluster.annotations_of(Logo) and not products
    assert texts["misread"] > 0 and texts["read"] > 5 * texts["misread"]
    cereal = [c for c, o in zip(clusters, observations, strict=True)
              if o.object == "corn_flakes#1"]
    labelled = [c.annotations_of(Classification)[0].class_name == "cereal" for c in cereal]
    assert np.mean(labelled) > 0.8
    assert any(p.properties["category"] == "breakfast cereal"
               for c in cereal for p in c.annotations_of(Product))
    log = week.scenes[0].log
    assert len({line.source for line in log}) == len(kw.ANNOTATORS)
    assert all(line.duration_ms > 0 for line in log if line.level == "info")


# --- consistency with the truth -------------------------------------------------------------


def test_clusters_are_the_objects_on_the_region_in_view(week):
    truth = week.truth
    for scene, seen in zip(week.scenes, truth.scenes, strict=True):
        t = scene.timestamp
        assert seen.time == t and len(scene.clusters) == len(seen.objects)
        assert sorted(truth.objects_on(seen.region, t)) == sorted(seen.objects)
        for i, cluster in enumerate(scene.clusters):
            object_id = truth.object_at(seen.index, i)
            location = cluster.annotations_of(Location)[0]
            assert location.region == seen.region == truth.where_at(object_id, t)
            error = np.subtract(location.position, truth.position_at(object_id, t))
            assert np.linalg.norm(error) < 0.06


def test_nothing_happens_while_the_robot_looks(week):
    truth = week.truth
    by_round = itertools.groupby(truth.scenes, key=lambda s: s.round)
    for _, scenes in by_round:
        scenes = list(scenes)
        assert [s.region for s in scenes] == list(kw.ROUTE)
        assert not truth.actions_between(scenes[0].time - 1, scenes[-1].time)


def test_only_the_region_in_view_is_in_the_camera_frustum(week):
    truth = week.truth
    for scene, seen in zip(week.scenes, truth.scenes, strict=True):
        for object_id in truth.objects:
            position = truth.position_at(object_id, seen.time)
            if position is None:
                continue
            pixels, depth = kw.project(scene.camera_pose, kw.corners(object_id, position))
            inside = ((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < 640)
                      & (pixels[:, 1] >= 0) & (pixels[:, 1] < 480))
            assert inside.all() == (object_id in seen.objects), (seen.index, object_id)
            assert inside.any() == (object_id in seen.objects), (seen.index, object_id)
        for cluster in scene.clusters:
            x, y, w, h = cluster.hypotheses[0].box
            assert w > 10 and h > 10 and x + w <= 640 and y + h <= 480


def test_gone_lists_what_the_robot_last_saw_there_and_is_missing(week):
    truth = week.truth
    for seen in truth.scenes:
        for object_id in seen.gone:
            before = [o for o in truth.observations_of(object_id) if o.scene < seen.index]
            assert truth.scenes[before[-1].scene].region == seen.region
            assert truth.where_at(object_id, seen.time) != seen.region


# --- appearance -----------------------------------------------------------------------------


def test_phash_is_stable_per_object_and_apart_across_objects(week):
    """Measured on seeds 0-2: the same object seen from the same side differs by a median of
    4 bits (95th percentile 12, worst 22); different kinds of object by a median of 28 (5th
    percentile 22, closest 10); the two sides of one object by a median of 22-26. The nearest
    other observation by pHash is of the same kind of object 99.7 % of the time."""
    observations = week.truth.observations
    hashes = np.array([int(c.hypotheses[0].phash, 16) for s in week.scenes for c in s.clusters],
                      dtype=np.uint64)
    keys = np.array([kw.item_of(o.object).key for o in observations])
    faces = np.array([o.face for o in observations])
    bits = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1)
    xor = (hashes[:, None] ^ hashes[None, :]).view(np.uint8)
    distance = bits[xor].reshape(len(hashes), len(hashes), 8).sum(axis=2)
    pairs = np.triu(np.ones_like(distance, bool), 1)
    same_kind = keys[:, None] == keys[None, :]
    same_face = faces[:, None] == faces[None, :]
    same = distance[pairs & same_kind & same_face]
    turned = distance[pairs & same_kind & ~same_face]
    other = distance[pairs & ~same_kind]
    assert np.median(same) <= 6 and np.percentile(same, 95) <= 14
    assert np.median(other) >= 26 and np.percentile(other, 5) >= 20
    assert np.median(turned) >= 16  # turning an object round is a new view
    np.fill_diagonal(distance, 64)
    assert np.mean(keys[distance.argmin(axis=1)] == keys) >= 0.99


def test_each_object_has_one_look_per_side():
    for item in kw.CATALOGUE.values():
        picture, mask = kw.render(item)
        again, _ = kw.render(item)
        assert np.array_equal(picture, again) and mask.any()
        if item.back is not None:
            back, _ = kw.render(item, "back")
            assert not np.array_equal(picture, back)
        first = kw.crop(item.key, "front", np.random.default_rng(1))
        assert first[0].shape == (kw.CROP, kw.CROP, 3) and first[1].shape == (kw.CROP, kw.CROP)


def test_misreadings_look_like_ocr_slips():
    rng = np.random.default_rng(3)
    readings = {kw.misread("Pringles Original", rng) for _ in range(200)}
    assert "Prinles Original" in readings
    assert all(len(r) >= len("Pringles Original") - 1 for r in readings)


# --- storage --------------------------------------------------------------------------------


def test_the_first_day_ingests_and_reads_back_equal(store):
    monday = kw.generate(days=1)
    items = ((f"kitchen week scene {i}", scene) for i, scene in enumerate(monday.scenes))
    landed = list(IngestService(store).ingest_stream(items))
    assert [scene for scene, _ in landed] == monday.scenes
    for scene, ids in landed:
        assert ids.created
        assert store.get_scene(ids.scene_id) == scene  # crops, masks and all
    assert store.counts()["collections"]["scenes"] == len(monday.scenes)
