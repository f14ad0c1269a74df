"""The graph-of-views object model and its similarity measures (Duceux 5.3).

A node is a view descriptor: a word of one modality's dictionary, written "modality:word"
(two nodes are equal when they are the same word of the same dictionary, 5.3.2). An edge is an
unordered pair of nodes perceived together (spatial: two modalities of one observation) or one
after the other (temporal: a change of view within a modality), written "a\\tb" with a <= b.
A model keeps nodes and edges as one set of strings, its *elements*, so that intersection and
union are set operations and |I| = |N_I| + |E_I| is its length.
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations

EDGE = "\t"


def node(modality: str, word: str) -> str:
    """A view descriptor; whitespace in a word becomes "_" (it separates the ends of edges)."""
    return f"{modality}:{'_'.join(str(word).split())}"


def edge(a: str, b: str) -> str:
    return f"{a}{EDGE}{b}" if a <= b else f"{b}{EDGE}{a}"


@lru_cache(maxsize=1 << 18)
def modality(element: str) -> str:
    """The modality (type) of a node, e.g. "shape", or of an edge, e.g. "colour-shape"
    (5.3.3: number_of(s - c, E))."""
    if EDGE in element:
        a, b = element.split(EDGE)
        return "-".join(sorted((modality(a), modality(b))))
    return element.split(":", 1)[0]


@dataclass(frozen=True, slots=True)
class GraphOfViews:
    """I = (N_I, E_I), as the set of its nodes and edges (5.3.2)."""

    elements: frozenset[str]

    @classmethod
    def of(cls, elements: Iterable[str]) -> GraphOfViews:
        """The graph of these elements, each string kept once in the process (sys.intern):
        equal elements of two models are then one object, so intersecting models, most of a
        learner's time, compares pointers instead of strings (a third faster)."""
        return cls(frozenset(map(sys.intern, elements)))

    @classmethod
    def of_sequence(cls, views: Iterable[Sequence[str]], after: Sequence[str] = ()
                    ) -> GraphOfViews:
        """The model of a sequence of observations, each a list of nodes: every node, an edge
        between the nodes of different modalities seen together, and an edge from each node to
        the nodes of its modality seen next that differ from it (the "blue"-"orange" edge of
        figure 5.2). `after`: the observation before the sequence, whose own nodes and edges a
        growing model holds already: only the edges from it to the sequence's first are added
        (a track grows by one observation at a time)."""
        elements: set[str] = set()
        previous = _by_modality(after)
        for observation in views:
            nodes = sorted(set(observation))
            elements.update(nodes)
            kinds = [(n, modality(n)) for n in nodes]  # (sorted: in each pair a <= b)
            elements.update(f"{a}{EDGE}{b}" for (a, kind_a), (b, kind_b)
                            in combinations(kinds, 2) if kind_a != kind_b)
            current = _by_modality(nodes)
            for kind, now in current.items():
                elements.update(edge(a, b) for a in previous.get(kind, ()) for b in now
                                if a != b)
            previous = current
        return cls.of(elements)

    def __len__(self) -> int:
        return len(self.elements)

    def __and__(self, other: GraphOfViews) -> GraphOfViews:
        return GraphOfViews(self.elements & other.elements)

    def __or__(self, other: GraphOfViews) -> GraphOfViews:
        return GraphOfViews(self.elements | other.elements)

    @property
    def nodes(self) -> frozenset[str]:
        return frozenset(e for e in self.elements if EDGE not in e)

    def kinds(self) -> set[str]:
        """The modalities present (modalities_number(G) is their number, 5.3.3)."""
        return set(map(modality, self.elements))

    def modalities(self) -> Counter:
        """number_of(t, G) for every type t present (5.3.3)."""
        return Counter(modality(e) for e in self.elements)


def _by_modality(nodes: Iterable[str]) -> dict[str, set[str]]:
    grouped: dict[str, set[str]] = {}
    for n in nodes:
        grouped.setdefault(modality(n), set()).add(n)
    return grouped


def intersection_size(i: GraphOfViews, j: GraphOfViews) -> int:
    """|I n J| (eq. 5.1)."""
    return len(i.elements & j.elements)


def inclusion_degree(i: GraphOfViews, j: GraphOfViews) -> float:
    """|I n J| / |I| (eq. 5.2): 1 when J explains all of I."""
    return Comparison(i, j).inclusion


def intersection_over_union(i: GraphOfViews, j: GraphOfViews) -> float:
    """|I n J| / |I u J| (eq. 5.3)."""
    union = len(i.elements | j.elements)
    return intersection_size(i, j) / union if union else 0.0


def modalities_match(i: GraphOfViews, j: GraphOfViews) -> int:
    """modalities_number(I n J) (eq. 5.5): in how many modalities the two agree at all."""
    return len((i & j).modalities())


def joint_modalities_intersection(i: GraphOfViews, j: GraphOfViews) -> int:
    """modalities_match(I, J) * |I n J| (eq. 5.6)."""
    common = i & j
    return len(common.modalities()) * len(common)


def normalized_jmi(i: GraphOfViews, j: GraphOfViews, max_modalities: int) -> float:
    """joint_modalities_intersection / (max_modalities * |I|) (eq. 5.7): normalised by the
    modalities of the whole system, so that a partial model agreeing in few modalities weighs
    less than one agreeing in many."""
    return Comparison(i, j).normalized_jmi(max_modalities)


class Comparison:
    """The measures of one pair (I, J) from a single intersection: a learner compares a new
    model with tens of others, each both ways and by its joint modalities (algorithm 5)."""

    __slots__ = ("common", "size_i", "size_j")

    def __init__(self, i: GraphOfViews, j: GraphOfViews):
        self.common = i.elements & j.elements
        self.size_i, self.size_j = len(i), len(j)

    @property
    def inclusion(self) -> float:
        """inclusion_degree(I, J), eq. 5.2."""
        return len(self.common) / self.size_i if self.size_i else 0.0

    @property
    def included(self) -> float:
        """inclusion_degree(J, I), eq. 5.2."""
        return len(self.common) / self.size_j if self.size_j else 0.0

    def normalized_jmi(self, max_modalities: int) -> float:
        """modalities_match * |I n J| / (max_modalities * |I|), eq. 5.7."""
        if not self.size_i:
            return 0.0
        matched = len(set(map(modality, self.common)))
        return matched * len(self.common) / (max_modalities * self.size_i)


def per_modalities_inclusion(i: GraphOfViews, j: GraphOfViews) -> float:
    """Sum over I's modalities of the share of each included in J (eq. 5.8), divided by their
    number as in the thesis' example (1.5 modalities of 3 in common gives 0.5)."""
    own = i.modalities()
    if not own:
        return 0.0
    common = (i & j).modalities()
    return sum(common[t] / n for t, n in own.items()) / len(own)


def modalities_consensus(i: GraphOfViews, j: GraphOfViews, known: Sequence[GraphOfViews]
                         ) -> float:
    """How far the modalities agree that J is I's best match among the known models M
    (eq. 5.12): per modality, I n J's count over the best count of any model of M, summed
    and divided by the number of modalities in M."""
    kinds: set[str] = set()
    best: Counter = Counter()
    for m in known:
        kinds.update(m.modalities())
        for t, n in (i & m).modalities().items():
            best[t] = max(best[t], n)
    if not kinds:
        return 0.0
    common = (i & j).modalities()
    return sum(n / best[t] for t, n in common.items() if best[t]) / len(kinds)
