"""The belief state kept by the consolidation stage, on the real store and the kitchen week."""

from __future__ import annotations

from collections import Counter

import pytest
from pymongo import MongoClient

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import IngestService, memory_pipeline
from percept_memory.memory.consolidation import Consolidation
from percept_memory.memory.identity import Calibration
from percept_memory.memory.pipeline import request_rebuild
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore
from percept_memory.memory.types import (
    Cluster,
    Location,
    Scene,
    SemanticColor,
    Shape,
    SpatialVolume,
)
from percept_memory.queries.engine import QueryEngine

from .conftest import ingest_consolidated
from .test_catalogue_store import stored_catalogue


@pytest.fixture(scope="module")
def week():
    return kitchen_week.generate(days=1)


@pytest.fixture(scope="module")
def consolidated(store, week):
    ingest_consolidated(store, week.scenes)
    return Consolidation(store)


def consolidate_one_by_one(store, scenes) -> None:
    """Each scene stored and consolidated before the next one comes (wait for the belief)."""
    service = IngestService(store)
    for scene in scenes:
        service.ingest(scene, wait=30)


def test_every_cluster_is_an_object_with_an_event(store, week, consolidated):
    clusters = sum(len(s.clusters) for s in week.scenes)
    assert store.clusters.count_documents({"object_id": None}) == 0
    seen = Counter(e["explanation"] for e in store.db.events.find({"cluster_id": {"$ne": None}}))
    assert sum(seen.values()) == clusters
    assert set(seen) <= {"appear", "stay", "move", "newview"}
    assert seen["stay"] > seen["appear"] > 0


def test_the_belief_matches_the_kitchen_week(store, week, consolidated):
    """Against the generated truth: an object never mixes two kinds of item (identical twins,
    such as three white cups, cannot be told apart once out of sight; kinds can), the real
    objects are not split into many, and at the end of the day the belief says what is on
    each surface (which of two identical cups it is, nobody can say)."""
    truth = {week.scenes[o.scene].clusters[o.cluster].id: o.object
             for o in week.truth.observations}
    kind_of = {}
    for doc in store.clusters.find({}, {"object_id": 1}):
        kind_of.setdefault(doc["object_id"], set()).add(truth[doc["_id"]].split("#")[0])
    assert all(len(kinds) == 1 for kinds in kind_of.values())
    assert len(kind_of) <= 1.3 * len(set(truth.values()))

    end = week.scenes[-1].timestamp
    believed = Counter((doc["region"], *kind_of[doc["_id"]])
                       for doc in store.db.objects.find({"state": {"$ne": "disappeared"}}))
    real = Counter((week.truth.where_at(item, end), item.split("#")[0])
                   for item in set(truth.values()) if week.truth.where_at(item, end))
    right = sum((believed & real).values())
    assert right >= 0.9 * sum(real.values()) and right >= 0.9 * sum(believed.values())


def test_events_keep_the_alternatives_with_probabilities(store, consolidated):
    for event in store.db.events.find({"cluster_id": {"$ne": None}}).limit(200):
        total = sum(a["probability"] for a in event["alternatives"])
        assert 0 < event["probability"] <= 1 and total <= 1 + 1e-9
        assert event["alternatives"] == sorted(event["alternatives"],
                                               key=lambda a: -a["probability"])


def test_objects_are_named_from_their_evidence(store, consolidated):
    ketchup = store.db.objects.find_one({"names": "ketchup"})
    assert ketchup is not None and ketchup["name"] in ("heinz", "heinz tomato ketchup", "ketchup")
    assert store.db.objects.count_documents({"name": "kellogg's"}) >= 1


@pytest.fixture
def empty_store(mongo_uri, db_name):
    """A store of its own, with no belief state yet."""
    client = MongoClient(mongo_uri, **CLIENT_OPTIONS)
    memory = MemoryStore(client, f"{db_name}_probe", gridfs_threshold=128 * 1024)
    memory.prepare()
    yield memory
    client.drop_database(f"{db_name}_probe")
    memory.close()


def test_out_of_view_is_hidden_and_a_place_seen_empty_is_disappeared(empty_store, week):
    """One object on the table; the robot looks at another region (hidden), then at the table
    again without it (disappeared). Camera poses of the kitchen week: the frustum decides."""
    store = empty_store
    table = next(s for s in week.scenes if s.clusters and s.clusters[0].region == "table")
    other = next(s for s in week.scenes if s.clusters and s.clusters[0].region == "shelf")
    mug = Cluster(annotations=[
        Location(region="table", position=table.clusters[0].position),
        SemanticColor(ratios={"blue": 1.0}), Shape(shape="cylinder")])
    base = 2_000_000_000_000_000_000
    scenes = [Scene(timestamp=base + i, robot="probe", camera_pose=view.camera_pose,
                    camera=view.camera, clusters=clusters)
              for i, (view, clusters) in enumerate([(table, [mug]), (other, []), (table, [])])]
    consolidate_one_by_one(store, scenes)
    mug_id = store.get_cluster(mug.id).object_id
    history = [e["explanation"] for e in store.db.events.find({"object_id": mug_id}).sort("time")]
    assert history == ["appear", "hidden", "disappear"]
    assert store.db.objects.find_one({"_id": mug_id})["state"] == "disappeared"


def test_a_declared_view_region_decides_what_was_in_view(empty_store):
    """A scene without a camera may say what its sensor covered: objects believed inside it
    and not seen disappeared, those outside are hidden."""
    store = empty_store

    def thing(x: float, colour: str) -> Cluster:
        return Cluster(annotations=[Location(position=(x, 0.0, 0.8)),
                                    SemanticColor(ratios={colour: 1.0}), Shape(shape="box")])

    def looking_at(x0: float, x1: float) -> SpatialVolume:
        return SpatialVolume(box_min=(x0, -1.0, 0.0), box_max=(x1, 1.0, 2.0))

    near, far = thing(0.2, "red"), thing(2.2, "green")
    base = 4_000_000_000_000_000_000
    scenes = [Scene(timestamp=base, robot="probe", clusters=[near, far],
                    view_region=looking_at(0.0, 3.0)),
              Scene(timestamp=base + 1, robot="probe", view_region=looking_at(0.0, 1.0))]
    consolidate_one_by_one(store, scenes)
    state = {c.id: store.db.objects.find_one({"_id": store.get_cluster(c.id).object_id})["state"]
             for c in (near, far)}
    assert state == {near.id: "disappeared", far.id: "hidden"}


def test_the_learnt_calibration_is_kept_with_the_belief(store, consolidated):
    """A new consolidator (another process, a restart) goes on with what its map learnt."""
    learnt = consolidated.calibration(kitchen_week.MAP)
    assert Consolidation(store).calibration(kitchen_week.MAP) == learnt
    assert learnt != Calibration.prior(consolidated.params)
    assert consolidated.calibration("another map") == Calibration.prior(consolidated.params)


def test_reconsolidation_is_deterministic(store, consolidated):
    def partition():
        groups: dict = {}
        for doc in store.clusters.find({}, {"object_id": 1}):
            groups.setdefault(doc["object_id"], set()).add(doc["_id"])
        return {frozenset(g) for g in groups.values()}

    def rebuild():
        request_rebuild(store)
        IngestService(store).pipeline.drain(timeout=600)

    rebuild()
    first = partition()
    rebuild()
    assert partition() == first
    assert store.db.objects.count_documents({}) == len(first)


def test_an_object_taken_away_and_brought_back_is_the_same_object(empty_store, week):
    store = empty_store
    table = next(s for s in week.scenes if s.clusters and s.clusters[0].region == "table")
    shelf = next(s for s in week.scenes if s.clusters and s.clusters[0].region == "shelf")

    def mug(view):
        return Cluster(annotations=[
            Location(region=view.clusters[0].region, position=view.clusters[0].position),
            SemanticColor(ratios={"blue": 1.0}), Shape(shape="cylinder")])

    base = 3_000_000_000_000_000_000
    first, back = mug(table), mug(shelf)
    scenes = [Scene(timestamp=base + i, robot="probe", camera_pose=view.camera_pose,
                    camera=view.camera, clusters=clusters)
              for i, (view, clusters) in enumerate([(table, [first]), (table, []),
                                                    (shelf, [back])])]
    consolidate_one_by_one(store, scenes)
    mug_id = store.get_cluster(first.id).object_id
    assert store.get_cluster(back.id).object_id == mug_id
    history = [e["explanation"] for e in store.db.events.find({"object_id": mug_id}).sort("time")]
    assert history == ["appear", "disappear", "move"]
    assert store.db.objects.find_one({"_id": mug_id})["state"] == "present"


def _box(colour: str, x: float) -> Cluster:
    return Cluster(annotations=[Location(region=f"table {x // 3:.0f}", position=(x, 0.0, 0.8)),
                                SemanticColor(ratios={colour: 1.0}), Shape(shape="box")])


def _looks(at: float, *clusters: Cluster, t: int) -> Scene:
    """A look at the table around x = at (tables 3 m apart), in a map of these tests'."""
    return Scene(timestamp=4_000_000_000_000_000_000 + t, robot="turner", map="sides",
                 view_region=SpatialVolume(box_min=(at - 0.6, -1.0, 0.0),
                                           box_max=(at + 0.6, 1.0, 2.0)),
                 clusters=list(clusters))


def test_an_object_is_recognised_by_any_side_it_was_seen_with(empty_store):
    """Seen red, turned blue where it stood, taken away, then found on another table showing
    red again: a move of the same object, not a new one (Known.others)."""
    red, blue, again = _box("red", 0.5), _box("blue", 0.5), _box("red", 3.5)
    consolidate_one_by_one(empty_store, [_looks(0.5, red, t=0), _looks(0.5, blue, t=1),
                                         _looks(0.5, t=2), _looks(3.5, again, t=3)])
    assert empty_store.db.objects.count_documents({"map": "sides"}) == 1
    event = empty_store.db.events.find_one({"cluster_id": again.id})
    assert event["explanation"] == "move"
    assert empty_store.get_cluster(again.id).object_id == empty_store.get_cluster(red.id).object_id


def test_one_object_remembered_twice_is_merged_when_its_sides_meet(empty_store):
    """Taken away red, found elsewhere showing a side never seen (blue): a new object, as
    nothing could tell. Turned back to red where it stands: the two never stood side by side
    and look the same, so they are one object, with one history."""
    red, blue, turned = _box("red", 0.5), _box("blue", 3.5), _box("red", 3.5)
    consolidate_one_by_one(empty_store, [_looks(0.5, red, t=0), _looks(0.5, t=1),
                                         _looks(3.5, blue, t=2), _looks(3.5, turned, t=3)])
    objects = list(empty_store.db.objects.find({"map": "sides"}))
    assert len(objects) == 1 and objects[0]["observations"] == 3
    assert {empty_store.get_cluster(c.id).object_id for c in (red, blue, turned)} == {
        objects[0]["_id"]}
    history = [e["explanation"] for e in empty_store.db.events.find(
        {"object_id": objects[0]["_id"]}).sort("time")]
    assert history == ["appear", "disappear", "move", "newview"]  # one object: one appear


def test_a_merge_in_a_batch_writes_what_the_batch_had_pending_of_both_objects(empty_store):
    """The scenes of the test above consolidated in one batch (a rebuild's, a backlog's): the
    merge comes while both objects' writes, events and links are still the batch's own, and
    the belief is the one scene by scene gives."""
    red, blue, turned = _box("red", 0.5), _box("blue", 3.5), _box("red", 3.5)
    IngestService(empty_store).ingest_batch([_looks(0.5, red, t=0), _looks(0.5, t=1),
                                             _looks(3.5, blue, t=2), _looks(3.5, turned, t=3)])
    memory_pipeline(empty_store).drain(timeout=60)
    objects = list(empty_store.db.objects.find({"map": "sides"}))
    assert len(objects) == 1 and objects[0]["observations"] == 3
    assert objects[0]["state"] == "present" and objects[0]["position"][0] == pytest.approx(3.5)
    assert {empty_store.get_cluster(c.id).object_id for c in (red, blue, turned)} == {
        objects[0]["_id"]}
    history = [e["explanation"] for e in empty_store.db.events.find(
        {"object_id": objects[0]["_id"]}).sort("time")]
    assert history == ["appear", "disappear", "move", "newview"]  # one object: one appear
    assert empty_store.db.events.count_documents({}) == 4


@pytest.mark.parametrize("batched", [False, True], ids=["scene by scene", "in one batch"])
def test_a_twin_seen_gone_in_the_scene_that_merges_it_keeps_no_event_of_it(empty_store,
                                                                          batched):
    """Red on one table, then a blue object on another; then a look over both tables: the
    red one is not where it was, and the blue one shows red. The two are one object, moved:
    "gone from the first table" in that look is no event of it, whether the scenes came one
    by one or in one batch (where the merge finds that event still the batch's own). Nor is
    "hidden on the first table" at the moment it was seen on the other: one object, one belief
    a scene, and an observation beats a guess."""
    red, blue, turned = _box("red", 0.5), _box("blue", 3.5), _box("red", 3.5)
    both_tables = _looks(2.0, turned, t=2)
    both_tables.view_region = SpatialVolume(box_min=(0.0, -1.0, 0.0), box_max=(4.0, 1.0, 2.0))
    scenes = [_looks(0.5, red, t=0), _looks(3.5, blue, t=1), both_tables]
    if batched:
        IngestService(empty_store).ingest_batch(scenes)
        memory_pipeline(empty_store).drain(timeout=60)
    else:
        consolidate_one_by_one(empty_store, scenes)
    (doc,) = empty_store.db.objects.find({"map": "sides"})
    history = [(e["time"] % 10, e["explanation"]) for e in empty_store.db.events.find(
        {"object_id": doc["_id"]}).sort("time")]
    assert history == [(0, "appear"), (1, "move"), (2, "newview")]
    assert empty_store.db.events.count_documents({}) == 3


def test_an_object_remembered_twice_keeps_the_id_of_its_longer_history(empty_store):
    """Seen red three times, taken away and found showing blue (a new object, for a while),
    then turned back to red: one object, under the id it was known by for longer, and where
    and as it is now."""
    reds, blue, turned = [_box("red", 0.5) for _ in range(3)], _box("blue", 3.5), _box("red", 3.5)
    consolidate_one_by_one(empty_store, [*(_looks(0.5, c, t=t) for t, c in enumerate(reds)),
                                         _looks(0.5, t=3), _looks(3.5, blue, t=4)])
    known_for_long = empty_store.get_cluster(reds[0].id).object_id
    assert empty_store.get_cluster(blue.id).object_id != known_for_long
    consolidate_one_by_one(empty_store, [_looks(3.5, turned, t=5)])
    (doc,) = empty_store.db.objects.find({"map": "sides"})
    assert doc["_id"] == known_for_long and doc["observations"] == 5
    assert doc["state"] == "present" and doc["position"][0] == pytest.approx(3.5)
    assert {empty_store.get_cluster(c.id).object_id for c in (*reds, blue, turned)} == {
        known_for_long}
    assert empty_store.db.events.count_documents({"object_id": {"$ne": known_for_long}}) == 0


def test_the_catalogue_learns_each_observation_as_the_object_it_was_by_then(empty_store):
    """Identity merges an object remembered twice in a later scene; whether the consolidator
    took the scenes one at a time (a busy server) or all in one batch (a rebuild), the
    catalogue learnt the earlier observations under the object they were then."""
    red, blue, again, turned = (_box("red", 0.5), _box("blue", 3.5), _box("blue", 3.5),
                                _box("red", 3.5))
    IngestService(empty_store).ingest_batch([
        _looks(0.5, red, t=0), _looks(0.5, t=1), _looks(3.5, blue, t=2), _looks(3.5, again, t=3),
        _looks(3.5, turned, t=4)])
    one_by_one = memory_pipeline(empty_store)
    one_by_one.batch = 1
    one_by_one.drain(timeout=60)
    assert empty_store.db.objects.count_documents({"map": "sides"}) == 1  # merged
    single = stored_catalogue(empty_store)
    request_rebuild(empty_store)
    memory_pipeline(empty_store).drain(timeout=60)
    assert stored_catalogue(empty_store) == single


def test_an_object_keeps_the_look_most_observations_showed(empty_store):
    """Seen red three times, then turned where it stood to four looks seen once each (more
    than the looks kept): red, the look most observations agreed on, is still known, so the
    object taken away and found red on another table is the same object, moved."""
    reds = [_box("red", 0.5) for _ in range(3)]
    turns = [_box(colour, 0.5) for colour in ("blue", "green", "yellow", "white")]
    again = _box("red", 3.5)
    consolidate_one_by_one(empty_store, [
        *(_looks(0.5, c, t=t) for t, c in enumerate([*reds, *turns])),
        _looks(0.5, t=7), _looks(3.5, again, t=8)])
    assert empty_store.db.events.find_one({"cluster_id": again.id})["explanation"] == "move"
    assert empty_store.db.objects.count_documents({"map": "sides"}) == 1


def test_lookalikes_seen_side_by_side_are_never_merged(empty_store):
    left, right, later = _box("red", 0.3), _box("red", 0.7), _box("red", 3.5)
    consolidate_one_by_one(empty_store, [_looks(0.5, left, right, t=0), _looks(3.5, later, t=1)])
    assert empty_store.db.objects.count_documents({"map": "sides"}) == 2


def test_an_objects_place_is_the_mean_of_its_observations_since_it_last_moved(empty_store):
    seen = [_box("green", x) for x in (0.50, 0.53, 0.47, 0.50)]
    moved = _box("green", 0.95)
    consolidate_one_by_one(empty_store, [_looks(0.6, c, t=i) for i, c in enumerate(seen)])
    (doc,) = empty_store.db.objects.find({"map": "sides"})
    assert doc["position"][0] == pytest.approx(0.50) and doc["place_count"] == 4
    consolidate_one_by_one(empty_store, [_looks(0.6, moved, t=9)])
    doc = empty_store.db.objects.find_one({"_id": doc["_id"]})
    assert empty_store.db.events.find_one({"cluster_id": moved.id})["explanation"] == "move"
    assert doc["position"][0] == pytest.approx(0.95) and doc["place_count"] == 1


def test_a_declared_position_noise_gives_the_place_estimate_its_variance(empty_store):
    """A sensor that declares its noise (Location.position_sigma, 4 cm here): the object's
    place is the mean of its observations, whose variance falls as 1/n; observations 8 cm
    apart, beyond the learnt spread of a sensor good to 2 cm, are one object staying."""
    seen = [_box("green", x) for x in (0.50, 0.58, 0.46, 0.54)]
    for cluster in seen:
        cluster.annotations[0].position_sigma = (0.04, 0.04, 0.0)
    consolidate_one_by_one(empty_store, [_looks(0.6, c, t=i) for i, c in enumerate(seen)])
    (doc,) = empty_store.db.objects.find({"map": "sides"})
    assert [e["explanation"] for e in empty_store.db.events.find().sort("time", 1)] == [
        "appear", "stay", "stay", "stay"]
    assert doc["position"][0] == pytest.approx(0.52) and doc["place_count"] == 4
    assert doc["position_variance"] == pytest.approx([0.0016 / 4, 0.0016 / 4, 0.0])
    (belief,) = QueryEngine(empty_store).where_is(str(doc["_id"]))
    assert belief.position_sigma == pytest.approx((0.02, 0.02, 0.0))


def test_candidates_are_given_to_identity_with_when_they_were_last_seen(empty_store,
                                                                         monkeypatch):
    """Identity prefers, of two look-alikes, the one seen last (Parameters.superseded): it
    must know when each candidate was last seen."""
    from percept_memory.memory import consolidation

    given, resolve = [], consolidation.resolve

    def spy(new, known, *args, **kwargs):
        given.append({k.key: k.last_seen for k in known})
        return resolve(new, known, *args, **kwargs)

    monkeypatch.setattr(consolidation, "resolve", spy)
    red, blue = _box("red", 0.3), _box("blue", 0.7)
    consolidate_one_by_one(empty_store, [_looks(0.5, red, t=0), _looks(0.5, blue, t=5),
                                         _looks(0.5, t=9)])
    ids = [empty_store.get_cluster(c.id).object_id for c in (red, blue)]
    start = 4_000_000_000_000_000_000
    assert given[-1] == {ids[0]: start, ids[1]: start + 5}
