"""A map's objects kept in memory by its consolidator (memory/known_objects.py): the objects
seen most recently must come out exactly as the objects' map_seen index gives them (last seen,
then last cluster, descending), or identity would decide on other candidates than a rebuild."""

from __future__ import annotations

import random

from bson import ObjectId

from percept_memory.memory.known_objects import KnownObjects


def _as_the_index_gives(docs: dict, limit: int, but: set) -> list:
    ordered = sorted(docs.values(), key=lambda d: (d["last_seen"], d["last_cluster"]),
                     reverse=True)
    return [d["_id"] for d in ordered if d["_id"] not in but][:limit]


def test_the_most_recently_seen_objects_come_in_the_index_order_ties_and_merges_included():
    rng = random.Random(7)
    known = KnownObjects(None)
    ids = [ObjectId() for _ in range(60)]
    now = 0
    for step in range(400):
        object_id = rng.choice(ids)
        if step % 50 == 49 and object_id in known.docs:  # merged into another: no more
            known.drop(object_id)
        elif step % 7 == 0 and object_id in known.docs:  # not seen: its state changes
            known.write(object_id, {"state": "hidden"})
        else:  # seen: now or at the time of the scene before (two clusters of one scene)
            now += rng.choice([0, 0, 1])
            known.write(object_id, {"state": "present", "last_seen": now,
                                    "last_cluster": ObjectId(rng.randbytes(12))},
                        first_seen=now)
        if step % 40 == 39:  # an object read again from the database after a merge
            again = rng.choice(list(known.docs))
            known.put(dict(known.docs[again]))
        but = set(rng.sample(list(known.docs), k=min(5, len(known.docs))))
        for limit in (1, 8, 32):
            assert [d["_id"] for d in known.recent(limit, but)] == _as_the_index_gives(
                known.docs, limit, but)


def test_an_object_not_seen_keeps_its_place_in_time_and_its_other_fields():
    known = KnownObjects(None)
    older, newer = ObjectId(), ObjectId()
    known.write(older, {"state": "present", "last_seen": 1, "last_cluster": ObjectId(),
                        "position": [1.0, 2.0, 0.5]}, first_seen=1)
    known.write(newer, {"state": "present", "last_seen": 2, "last_cluster": ObjectId()},
                first_seen=2)
    known.write(older, {"state": "hidden"})
    assert [d["_id"] for d in known.recent(2, set())] == [newer, older]
    assert known.docs[older]["state"] == "hidden"
    assert known.docs[older]["position"] == [1.0, 2.0, 0.5]
    assert known.docs[older]["first_seen"] == 1
