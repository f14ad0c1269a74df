"""bench/belief.py's ground truth is consistent with itself: it asks for an id only where a
memory could know it (no database: the run's bookkeeping alone)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(autouse=True, scope="module")
def bench_types_forgotten():
    """bench/identity.py registers a bench-only annotation type (bench.annotation.Colour):
    forgotten after this module, so the rest of the suite sees the program's types alone (the
    published interchange schema lists every registered annotation type)."""
    from percept_memory.converters import registry

    by_name, by_class = dict(registry._class_by_name), dict(registry._name_by_class)
    yield
    registry._class_by_name.clear()
    registry._class_by_name.update(by_name)
    registry._name_by_class.clear()
    registry._name_by_class.update(by_class)


@pytest.fixture
def run(monkeypatch):
    """A long run's bookkeeping after real object 0 was seen showing side 0 as id "J", then
    moved and turned to side 1, never seen, which rightly got a new id "K"."""
    monkeypatch.syspath_prepend(str(BENCH))
    import belief

    run = belief.LongRun(seed=1, noise=0.025, decider=SimpleNamespace(merged=[]),
                         where_samples=0)
    run.world.place = {0: np.array([0.2, 0.1])}
    run.world.side[0] = 1
    run.last_id, run.last_place, run.last_side = {0: "K"}, {0: np.array([0.2, 0.1])}, {0: 1}
    run.seen_as = {(0, 0): "J", (0, 1): "K"}
    run.ids = {"J", "K"}
    return run


def test_moved_and_turned_back_the_object_is_the_id_that_saw_that_side(run):
    """K never saw side 0: after a move nothing could know K by it, only J (the id that did)."""
    run.world.place[0] = np.array([3.2, 0.1])
    run.world.side[0] = 0
    assert run.expected_id(0) == "J"
    assert run.known_look(0, {"J": object(), "K": object()}) == "J"


def test_turned_where_it_stood_or_moved_as_it_was_the_object_is_its_last_id(run):
    run.world.side[0] = 0  # turned in place: the place tells
    assert run.expected_id(0) == "K"
    run.world.side[0] = 1
    run.world.place[0] = np.array([3.2, 0.1])  # moved showing the side K saw
    assert run.expected_id(0) == "K"


def test_moved_and_turned_to_a_side_never_seen_is_a_new_object(run):
    del run.seen_as[0, 0]
    run.world.place[0] = np.array([3.2, 0.1])
    run.world.side[0] = 0
    assert run.expected_id(0) is None
    assert run.known_look(0, {"K": object()}) is None


def test_where_is_is_scored_apart_for_the_objects_not_moved_since_last_observed(run):
    """An object brought back unseen to the table it was last observed on, at another spot,
    was moved unseen: a memory that saw it go rightly says "disappeared". It is not among
    the objects a memory can know, as "still on the table last seen on" once counted it."""
    import belief

    answers = {"K": {"state": "disappeared", "region": "table_0", "position": [0.2, 0.1, 0]}}
    run.decider = SimpleNamespace(server=SimpleNamespace(where_is=answers.get))
    run.where_samples = 1
    extra = belief.Extra()
    run.world.place[0] = np.array([-0.3, 0.2])  # back on table 0, elsewhere
    run.where(extra)
    assert (extra.right_table, extra.right_table_unmoved) == ([0, 1], [0, 0])
    run.world.place[0] = np.array([0.2, 0.1])  # where it was last observed, believed hidden
    answers["K"]["state"] = "hidden"
    run.where(extra)
    assert (extra.right_table, extra.right_table_unmoved) == ([1, 2], [1, 1])
    assert extra.near_unmoved == [1, 1]


def test_the_moves_are_scored_apart_by_how_far_they_went(run):
    """A nudge within the noise is no move to any memory: the moves of new clusters are
    counted apart under 0.5 m (nudges) and from 0.5 m on, each with whether it was called a
    move."""
    import belief
    from identity import Belief, Score

    from percept_memory.memory.identity import Decision, Explanation, Observation

    seen = Observation((0, 1), (0.2, 0.1, 0.0))
    run.belief = {"K": Belief(seen, 0), "L": Belief(seen, 1)}
    run.belief["K"].true_place, run.belief["L"].true_place = np.array([0.0, 0.1]), np.array(
        [2.0, 0.1])
    run.world.place = {0: np.array([0.2, 0.1]), 1: np.array([3.2, 0.1])}
    decisions = [Decision((0, 2), "K", Explanation.STAY, 0.9),
                 Decision((1, 3), "L", Explanation.MOVE, 0.9)]
    run.score(Score(), decisions, [], {0: ("K", "move"), 1: ("L", "move")}, 0.0)
    assert run.moves == {belief.NUDGED: [0, 1], belief.FAR: [1, 1]}


def test_a_scene_is_scored_as_it_left_the_memory_after_its_merges(run):
    """The memory found in this scene that "K", just seen, is "J", remembered for longer, and
    kept J's id: the observation answered "J" is right where the truth still expected "K",
    and K, merged into J, is no object remembered but unseen."""
    from identity import Known, Score

    from percept_memory.memory.identity import Decision, Explanation, Observation

    seen = Observation((0, 5), (0.2, 0.1, 0.0))
    run.decider.merged = [("K", "J")]
    score = Score()
    run.score(score, [Decision((0, 5), "J", Explanation.NEWVIEW, 0.9),
                      Decision("K", "K", Explanation.HIDDEN, 1.0)],
              [Known("K", seen, True)], {0: ("K", "newview")}, 0.0)
    assert score.associations == [1, 1] and score.explanations == [1, 1]
