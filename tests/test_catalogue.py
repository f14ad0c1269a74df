"""The long-term catalogue's core: graphs of views, the thesis' measures, incremental learning
by graph clustering (merging duplicates, splitting corrupted clusters)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from percept_memory.memory.catalogue.graph_of_views import (
    GraphOfViews,
    edge,
    inclusion_degree,
    intersection_over_union,
    intersection_size,
    joint_modalities_intersection,
    modalities_consensus,
    modalities_match,
    node,
    normalized_jmi,
    per_modalities_inclusion,
)
from percept_memory.memory.catalogue.learning import Change, Learner, Parameters
from percept_memory.memory.types import annotations as a
from percept_memory.memory.types.hypotheses import ImageROI


def seq(*views: int) -> GraphOfViews:
    return GraphOfViews.of_sequence([[node("v", v)] for v in views])


def test_a_sequence_gives_its_views_and_transitions():
    g = GraphOfViews.of_sequence([["shape:box", "color:blue"], ["shape:box", "color:orange"]])
    assert g.elements == {"shape:box", "color:blue", "color:orange",
                          edge("shape:box", "color:blue"), edge("shape:box", "color:orange"),
                          edge("color:blue", "color:orange")}
    # the thesis' example E = (s,0) - (c,0) - (c,1): 4 modalities s, c, s-c, c-c
    assert g.modalities() == {"shape": 1, "color": 2, "color-shape": 2, "color-color": 1}


def test_the_measures_of_5_3_3_and_5_3_4():
    i, j = seq(1, 2, 3, 4), seq(3, 4, 5)
    assert intersection_size(i, j) == 3  # views 3, 4 and edge 3-4
    assert inclusion_degree(i, j) == 3 / 7 and inclusion_degree(j, i) == 3 / 5
    assert intersection_over_union(i, j) == 3 / 9
    assert modalities_match(i, j) == 2
    assert joint_modalities_intersection(i, j) == 6
    assert normalized_jmi(i, j, max_modalities=2) == 6 / 14
    assert per_modalities_inclusion(i, j) == (2 / 4 + 1 / 3) / 2
    other = seq(1, 9)
    # j agrees with i more than any other known model in both modalities
    assert modalities_consensus(i, j, [j, other]) == 1.0
    assert modalities_consensus(i, other, [j, other]) == (1 / 2 + 0) / 2


def test_views_come_from_the_types_declaring_them():
    h = np.zeros((4, 4))
    h[1, 2], h[3, 3] = 5, 2
    assert a.ColorHistogram(histogram=h).views() == ["HS6", "HS15"]
    assert a.Text(text="Milk, whole milk 1L").views() == ["1l", "milk", "whole"]
    assert ImageROI(box=(0, 0, 2, 2), phash="0123456789abcdef").views() == [
        "0.0123", "1.4567", "2.89ab", "3.cdef"]
    vector = np.linspace(-1, 1, 32)
    near = vector + 0.01
    words = a.FeatureVector(name="vfh", vector=vector).views()
    assert len(words) == 4 and words == a.FeatureVector(name="vfh", vector=near).views()
    assert a.Location(region="table").views() == []


def learner(**overrides) -> Learner:
    return Learner(Parameters(**{"max_models_per_cluster": 3, **overrides}))


def test_a_new_view_merges_two_duplicates():
    """The front and the back of one object share nothing: two clusters, until a model seeing
    both sides links them (figure 6.6)."""
    memory = learner()
    memory.learn(1, seq(*range(0, 10)), 10)
    memory.learn(2, seq(*range(20, 30)), 10)
    assert len(memory.members) == 2
    memory.learn(3, seq(*range(5, 25)), 20)
    assert list(memory.members.values()) == [{1, 2, 3}]
    assert memory.classify(seq(0, 1, 2))[0] == (1, 1.0)
    assert memory.history == [Change("merged", (1, 2), (1,))]


def test_links_weigh_over_the_modalities_the_catalogue_holds():
    """max_modalities of eq. 5.7 is, unless set, modalities_number(M) of the models known (as
    in eq. 5.12): two models agreeing in all their modalities are alike however many kinds of
    evidence the program knows, and a kind of evidence no model holds any more weighs nothing."""
    memory = learner()
    memory.learn(1, seq(1, 2, 3, 4), 4)
    memory.learn(2, seq(3, 4, 5, 6), 4)  # v and v-v: 2 modalities
    assert memory.edges[2] == {1: normalized_jmi(seq(3, 4, 5, 6), seq(1, 2, 3, 4), 2)}
    memory.learn(3, GraphOfViews.of_sequence([["w:1"], ["w:2"]]), 2)  # and w, w-w
    memory.learn(4, seq(5, 6, 7, 8), 4)
    assert memory.edges[4] == {2: normalized_jmi(seq(5, 6, 7, 8), seq(3, 4, 5, 6), 4)}
    memory.forget(3)
    memory.learn(5, seq(7, 8, 9, 10), 4)
    assert memory.edges[5] == {4: normalized_jmi(seq(7, 8, 9, 10), seq(5, 6, 7, 8), 2)}


def test_a_model_included_in_another_is_discarded():
    memory = learner()
    memory.learn(1, seq(*range(0, 20)), 20)
    memory.learn(2, seq(*range(2, 12)), 10)
    assert set(memory.models) == {1}
    memory.learn(3, seq(*range(0, 40)), 40)  # now 1 adds nothing to 3
    assert set(memory.models) == {3} and memory.members == {3: {3}}


def test_a_discarded_model_passes_on_its_neighbours_as_alike_as_they_are_to_the_includer():
    """Model 1 is linked to model 2 by the views 15-19 they share; model 3 includes model 1 but
    shares only 15-17 with model 2: discarding 1 must not give 3 the 1-2 edge's weight."""
    memory = learner(high_inclusion=0.75, low_similarity=0.2)
    memory.learn(1, seq(*range(10, 20)), 10)
    memory.learn(2, seq(*range(15, 30)), 15)
    assert memory.edges[1] == {2: pytest.approx(9 / 29)}
    memory.learn(3, seq(*range(0, 18)), 18)  # 1 adds nothing to 3: discarded
    assert set(memory.models) == {2, 3}
    assert memory.edges == {2: {}, 3: {}}  # 3 and 2: 5 / 35 alike, below 0.2
    assert memory.members == {2: {2}, 3: {3}}


def test_a_new_model_discards_the_models_it_explains_even_when_another_explains_it():
    """A short look at views 20-27 of object A shares 20-23 with object B and joins B. A later
    look at A (5-27) explains it entirely, but is itself explained by A's model 0-24 compared
    first: the short look must go all the same (algorithm 5, line 10), not stay on B."""
    memory = learner(high_inclusion=0.75, low_similarity=0.3)
    memory.learn(1, seq(*range(50, 61), *range(20, 24)), 15)  # B
    memory.learn(2, seq(*range(20, 28)), 8)  # the short look at A, joins B
    memory.learn(3, seq(*range(0, 25)), 25)  # A
    assert memory.members == {1: {1, 2}, 3: {3}}
    memory.learn(4, seq(*range(5, 28)), 23)  # A again
    assert memory.members == {1: {1}, 3: {3}}


def test_a_corrupted_cluster_splits_at_its_weakest_edge():
    """Two objects sharing a few views were joined by a weak edge; when the cluster grows past
    its limit the weak edge is cut and each object keeps its own (algorithm 6)."""
    memory = learner()
    a_views, b_views = list(range(0, 12)), list(range(10, 22))
    memory.learn(1, seq(*a_views[:8]), 8)
    memory.learn(2, seq(*b_views[:8]), 8)
    memory.learn(3, seq(*a_views[4:]), 8)  # shares views 10, 11 with object b's model 2
    assert memory.cluster_of[2] == memory.cluster_of[1]  # corrupted
    memory.learn(4, seq(*b_views[4:]), 8)
    clusters = sorted(sorted(members) for members in memory.members.values())
    assert clusters == [[1, 3], [2, 4]]
    assert memory.history == [Change("merged", (1, 2), (1,)), Change("split", (1,), (1, 2))]


def test_a_model_learnt_again_notes_only_what_changed_net():
    """A grown model is forgotten and learnt again: the entry it bridges falls apart and comes
    together in one step, which is no change to note."""
    memory = learner()
    memory.learn(1, seq(*range(0, 10)), 10)
    memory.learn(2, seq(*range(20, 30)), 10)
    memory.learn(3, seq(*range(5, 25)), 20)
    memory.history.clear()
    memory.learn(3, seq(*range(5, 26)), 21)
    assert list(memory.members.values()) == [{1, 2, 3}] and memory.history == []
    memory.forget(3)
    assert memory.history == [Change("split", (1,), (1, 2))]


def test_singletons_beyond_the_limit_are_forgotten_shortest_first():
    memory = learner(max_singletons=2)
    for model_id, length in ((1, 5), (2, 3), (3, 9)):
        memory.learn(model_id, seq(100 * model_id, 100 * model_id + 1), length)
    assert set(memory.models) == {1, 3} and memory.singletons == {1, 3}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_index_stays_the_union_of_each_cluster(seed):
    """After any sequence of learning and forgetting, classification reads exactly the
    clusters' unions, and the clusters are the components of the graph."""
    rng = np.random.default_rng(seed)
    memory = learner(max_singletons=5)
    for model_id in range(120):
        start = int(rng.integers(0, 60))
        memory.learn(model_id, seq(*(int(v) for v in rng.integers(start, start + 12, 8))), 8)
        if model_id % 7 == 6 and memory.models:
            memory.forget(min(memory.models))
    for name, members in memory.members.items():
        expected = frozenset().union(*(memory.models[m].graph.elements for m in members))
        assert memory.union(name).elements == expected
        assert all(memory.cluster_of[m] == name for m in members)
        assert all(set(memory.edges[m]) <= members for m in members)
        assert len(members) <= 3 and all(len(memory.edges[m]) <= 2 for m in members)
    assert set(memory.cluster_of) == set(memory.models)
    holders: dict = {}
    for name in memory.members:
        for element in memory.union(name).elements:
            holders.setdefault(element, set()).add(name)
    # (an element of one cluster's union is indexed by the cluster itself, not a set of one)
    assert all(len(h) > 1 for h in memory._index.values() if type(h) is set)
    assert {e: h if type(h) is set else {h} for e, h in memory._index.items()} == holders


LEARN_IN_A_PROCESS = """
import numpy as np
from percept_memory.memory.catalogue.graph_of_views import GraphOfViews, node
from percept_memory.memory.catalogue.learning import Change, Learner, Parameters
rng = np.random.default_rng(0)
memory = Learner(Parameters(max_singletons=10, high_inclusion=0.75, low_similarity=0.2))
for i in range(400):  # 10 objects of 14 views, seen 6 at a time, some with a stray view
    start = int(rng.integers(0, 10)) * 10
    views = [int(v) for v in rng.integers(start, start + 14, 6)]
    if rng.random() < 0.1:
        views[0] = int(rng.integers(1000, 2000))
    graph = GraphOfViews.of_sequence([[node("v", v)] for v in views])
    memory.learn(i.to_bytes(12, "big"), graph, 6)
print(sorted(sorted(m.hex() for m in members) for members in memory.members.values()))
"""


def test_what_is_learnt_does_not_depend_on_the_process_hash_seed():
    """Models are named by ids' bytes, whose hashes (and so the order of sets of them) change
    with each process's hash seed: a rebuild in another process must learn the same."""
    runs = {subprocess.run([sys.executable, "-c", LEARN_IN_A_PROCESS], check=True,
                           capture_output=True, text=True,
                           env={**os.environ, "PYTHONHASHSEED": seed}).stdout
            for seed in ("1", "2", "3", "4")}
    assert len(runs) == 1
