"""Unsupervised, incremental object learning by graph clustering (Duceux 6.3.3).

Every partial model (the graph of views of one observation run of an object) is a node of a
similarity graph that keeps only each node's strongest edges (algorithm 5); the clusters, the
objects learnt, are its connected components (algorithm 9), cut at their weakest edges when they
hold more than a few models (algorithm 6); singletons beyond a limit are forgotten, the shortest
observation first (algorithm 7). A new model is compared only with the clusters that classify it
best (algorithm 3) and the singletons, and whatever it changes (a merge of two duplicates, a
corrupted cluster split) is local (algorithm 8). No decision is final: a later model can undo it.

Classification reads an inverted index (element -> clusters whose union holds it), so learning a
model costs what the model shares with the memory, not the size of the memory.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import chain

from .graph_of_views import Comparison, GraphOfViews


@dataclass(frozen=True)
class Parameters:
    """The thesis' settings on its real data set (6.4.2): thresholds 0.95 and 0.01, 5 models
    per cluster and so 4 edges per node, the 2 best clusters, 30 singletons."""

    high_inclusion: float = 0.95  # a model this much included in another adds nothing to it
    low_similarity: float = 0.01  # below: the two models do not belong together
    max_models_per_cluster: int = 5
    closest_clusters: int = 2  # k of algorithm 8
    max_singletons: int = 30
    compared_singletons: int = 30  # the singletons a new model is compared with, most alike first
    recognised: float = 0.95  # classification score "near 1": only its cluster is updated
    # normalising the similarity (eq. 5.7); None: the modalities of the models known (below)
    max_modalities: int | None = None
    common_element: int = 32  # held by more clusters than this, it finds no candidates

    @property
    def max_edges(self) -> int:
        """One less than the models of a cluster: exactly a fully connected cluster (6.3.3)."""
        return self.max_models_per_cluster - 1


@dataclass(frozen=True, slots=True)
class Change:
    """Entries (clusters, by name) that became one (`merged`: several before, one after) or
    several (`split`: one before, the parts it went to after): the learning people may want to
    follow (Duceux figure 6.6: a later view merges duplicates, a cut separates two objects)."""

    kind: str
    before: tuple
    after: tuple


@dataclass(frozen=True, slots=True)
class PartialModel:
    graph: GraphOfViews
    length: float  # how much was observed: the shortest singleton is forgotten first
    kinds: frozenset  # its modalities, found once (a pass over its elements)

    @classmethod
    def of(cls, graph: GraphOfViews, length: float) -> PartialModel:
        return cls(graph, length, frozenset(graph.kinds()))


class Learner:
    """The similarity graph and its clusters. Model ids must be ordered (ObjectIds, ints): a
    cluster is named by its smallest model id, so it keeps its name while that model stays."""

    def __init__(self, params: Parameters | None = None):
        self.params = params or Parameters()
        self.models: dict[Hashable, PartialModel] = {}
        self.edges: dict[Hashable, dict[Hashable, float]] = {}
        self.cluster_of: dict[Hashable, Hashable] = {}
        self.members: dict[Hashable, frozenset] = {}
        self.singletons: set[Hashable] = set()
        self._union: dict[Hashable, Counter] = {}  # cluster -> element -> models holding it
        # element -> the clusters whose union holds it: the cluster itself when it is the only
        # one (most elements: a set each cost a fifth of a learner's memory), else their set
        self._index: dict[str, Hashable | set[Hashable]] = {}
        self._dissolved: set[Hashable] = set()  # clusters to recompute
        self._modalities: Counter = Counter()  # modality -> models holding it
        self.changed: set[Hashable] = set()  # models added, removed, relinked or moved
        self.history: list[Change] = []  # entries merged or split, oldest first
        self._before: dict[Hashable, Hashable] = {}  # see _noting_changes

    # --- classification (algorithm 3) ---------------------------------------------------------

    def classify(self, graph: GraphOfViews) -> list[tuple[Hashable, float]]:
        """The clusters sharing something with the graph, with inclusion(g, c) (eq. 6.2), best
        first (ties by cluster name). The candidates are the clusters sharing an element that
        few clusters hold (as a text retrieval engine skips stop words); only when there is
        none, those sharing common ones ("box", "red"). A candidate's score is exact."""
        alone, rare, common = [], [], []
        for element in graph.elements:
            clusters = self._index.get(element)
            if clusters is None:
                continue
            if type(clusters) is not set:
                alone.append(clusters)
            else:
                (common if len(clusters) > self.params.common_element else rare).append(clusters)
        # counted in one call each: a model shares hundreds of elements with the memory
        hits = Counter(alone)
        hits.update(chain.from_iterable(rare))
        if hits:
            found = set(hits)  # once: a keys view & a set builds a set from the keys each time
            hits.update(chain.from_iterable(clusters & found for clusters in common))
        else:
            hits.update(chain.from_iterable(common))
        n = len(graph)
        return sorted(((c, k / n) for c, k in hits.items()), key=lambda x: (-x[1], x[0]))

    def union(self, cluster: Hashable) -> GraphOfViews:
        """The cluster's models merged into one (6.3.3: the union of partial models)."""
        return GraphOfViews(frozenset(self._union[cluster]))

    # --- learning (algorithm 8) ---------------------------------------------------------------

    def learn(self, model_id: Hashable, graph: GraphOfViews, length: float) -> None:
        """Take in a partial model (again, when its observation grew)."""
        with self._noting_changes():
            if model_id in self.models:
                self._recluster(self._remove(model_id))
            self._learn(model_id, graph, length)

    def _learn(self, model_id: Hashable, graph: GraphOfViews, length: float) -> None:
        ranked = self.classify(graph)
        self._add(model_id, PartialModel.of(graph, length))
        touched = {model_id}
        if ranked and ranked[0][1] >= self.params.recognised:
            touched |= self._update_similarity_graph(model_id, sorted(self.members[ranked[0][0]]))
        elif ranked:  # in between (nothing in common: a singleton, line 5)
            best = [c for c, _ in ranked[:self.params.closest_clusters]]
            near_singletons = [c for c, _ in ranked if c in self.singletons]
            compared = [m for c in best for m in sorted(self.members[c])]
            compared += [c for c in near_singletons[:self.params.compared_singletons]
                         if c not in best]
            touched |= self._update_similarity_graph(model_id, compared)
        self._recluster(touched)
        self._reduce_singletons()

    @classmethod
    def restored(cls, params: Parameters, models: Iterable[tuple]) -> Learner:
        """A learner from its stored models: (id, graph, length, {neighbour: weight})."""
        learner = cls(params)
        rows = list(models)
        for model_id, graph, length, _ in rows:
            learner._add(model_id, PartialModel.of(graph, length))
        for model_id, _, _, edges in rows:
            for other, weight in edges.items():
                if other in learner.models:
                    learner._link(model_id, other, weight)
        learner._recluster(set(learner.models))
        learner.changed.clear()
        learner.history.clear()
        return learner

    def forget(self, model_id: Hashable) -> None:
        """Remove a model and its edges (its cluster is recomputed)."""
        with self._noting_changes():
            self._recluster(self._remove(model_id))

    # --- algorithm 5: the similarity graph --------------------------------------------------

    def _update_similarity_graph(self, g: Hashable, compared: Iterable[Hashable]) -> set:
        """Algorithm 5, its line 10 first: every compared model the new one explains is
        discarded before the loop may return at line 8 (the new model itself explained by
        another). In the thesis' single loop, a small model the new one includes is kept or
        not by the order of M: a part two objects share, stuck on the wrong one, stayed."""
        p = self.params
        touched: set = set()
        graph = self.models[g].graph
        pairs = [(m, Comparison(graph, self.models[m].graph)) for m in compared
                 if m != g and m in self.models]
        for m, pair in pairs:
            if pair.included > p.high_inclusion >= pair.inclusion:  # m adds nothing
                touched |= self._absorb(m, g)
        for m, pair in pairs:
            if m not in self.models:
                continue
            if pair.inclusion > p.high_inclusion:  # g adds nothing to m
                touched |= self._absorb(g, m)
                return touched
            weight = self._similarity(pair)
            if weight > p.low_similarity:
                self._link(g, m, weight)
                touched |= {m} | self._filter_edges(g) | self._filter_edges(m)
        return touched

    def _similarity(self, pair: Comparison) -> float:
        """normalized_jmi (eq. 5.7) over max_modalities, "the maximum number of modalities
        considered in the system": unless set, those present in the models known, as
        modalities consensus (eq. 5.12) counts modalities_number(M). A home's perception
        produces a few of the kinds of evidence registered: normalised by all of them (77
        with their pairs), two models agreeing in all their modalities, an RGB histogram's
        bins and their changes, weighed 2/77 and never linked."""
        return pair.normalized_jmi(self.params.max_modalities or len(self._modalities))

    def _absorb(self, gone: Hashable, into: Hashable) -> set:
        """Discard a model; its neighbours become the including model's, then filtered (lines
        6-7). Each new edge weighs how alike the two models it joins are: the discarded
        model's weight measured the discarded model, which may be a part two objects share
        (copied, it made corrupted clusters at 2 of 20 tuning seeds of bench/catalogue.py)."""
        for other in self.edges[gone]:
            if other != into and other not in self.edges[into]:
                weight = self._similarity(Comparison(self.models[into].graph,
                                                     self.models[other].graph))
                if weight > self.params.low_similarity:
                    self._link(into, other, weight)
        touched = self._remove(gone)
        return touched | {into} | self._filter_edges(into)

    def _filter_edges(self, m: Hashable) -> set:
        """Keep the model's max_edges strongest edges: returns the models that lost one."""
        links = self.edges[m]
        lost = set()
        while len(links) > self.params.max_edges:
            weakest = min(links, key=lambda other: (links[other], other))
            self._unlink(m, weakest)
            lost.add(weakest)
        return lost

    # --- algorithms 9, 6, 7: clusters -------------------------------------------------------

    def _recluster(self, touched: set) -> None:
        """The connected components around what changed (algorithm 9), reduced (algorithm 6).
        A part keeps the cluster of its name (its smallest model) and is reshaped from it by
        the models that left and joined: a cluster's union and index entries are the costly
        part, and a new model or a cut moves one or two models, not the whole cluster."""
        dissolved = self._dissolved | {self.cluster_of[t] for t in touched
                                       if t in self.cluster_of}
        nodes = {m for c in dissolved for m in self.members[c]} | touched
        nodes = {m for m in nodes if m in self.models}
        self._dissolved = set()
        for m in nodes:
            if m in self.cluster_of:
                self._before.setdefault(m, self.cluster_of[m])
        parts = [part for component in self._components(nodes)
                 for part in self._reduced(component)]
        kept = {name for part in parts if (name := min(part)) in dissolved
                and self.members[name] - part <= self.models.keys()}
        for name in dissolved - kept:
            self._drop_cluster(name)
        for part in parts:
            if (name := min(part)) in kept:
                self._reshape_cluster(name, part)
            else:
                self._make_cluster(part)

    @contextmanager
    def _noting_changes(self) -> Iterator[None]:
        """Around one learning step: the entries it merged or split, net (a grown model is
        forgotten and learnt again; only where its models end up counts), into `history`."""
        self._before = {}  # model -> its cluster before the step, for those reclustered
        yield
        now_of: dict = {}  # a cluster now -> the clusters its models were in
        went_to: dict = {}  # a cluster before -> the clusters its models are in now
        for m, before in self._before.items():
            if m in self.cluster_of:
                now_of.setdefault(self.cluster_of[m], set()).add(before)
                went_to.setdefault(before, set()).add(self.cluster_of[m])
        self.history += [Change("merged", tuple(sorted(before)), (now,))
                         for now, before in sorted(now_of.items()) if len(before) > 1]
        self.history += [Change("split", (before,), tuple(sorted(now)))
                         for before, now in sorted(went_to.items()) if len(now) > 1]

    def _components(self, nodes: set) -> Iterator[set]:
        todo = set(nodes)
        while todo:
            start = todo.pop()
            component, stack = {start}, [start]
            while stack:
                for other in self.edges[stack.pop()]:
                    if other not in component:
                        component.add(other)
                        stack.append(other)
            todo -= component
            yield component

    def _reduced(self, component: set) -> Iterator[set]:
        """Cut a too-large cluster at its weakest edge until every part is small enough."""
        stack = [component]
        while stack:
            part = stack.pop()
            if len(part) <= self.params.max_models_per_cluster:
                yield part
                continue
            a, b = min(((a, b) for a in part for b in self.edges[a] if a < b),
                       key=lambda e: (self.edges[e[0]][e[1]], e))
            self._unlink(a, b)
            stack.extend(self._components(part))

    def _reduce_singletons(self) -> None:
        """Forget the shortest observations among the singletons beyond the limit."""
        while len(self.singletons) > self.params.max_singletons:
            shortest = min(self.singletons, key=lambda s: (self.models[s].length, s))
            self._remove(shortest)

    # --- bookkeeping ------------------------------------------------------------------------

    def _add(self, m: Hashable, model: PartialModel) -> None:
        self.models[m] = model
        self._modalities.update(model.kinds)
        self.edges[m] = {}
        self.changed.add(m)

    def _remove(self, m: Hashable) -> set:
        """Take a model out of the graph and out of its cluster (whose union loses its
        elements now, while they are known: the cluster left is reshaped, not rebuilt)."""
        neighbours = set(self.edges[m])
        for other in neighbours:
            self._unlink(m, other)
        cluster = self.cluster_of.pop(m, None)
        if cluster is not None:
            self._reshape_cluster(cluster, self.members[cluster] - {m})
            if self.members[cluster]:
                self._dissolved.add(cluster)
            else:
                self._dissolved.discard(cluster)
                self._drop_cluster(cluster)
        self._modalities.subtract(self.models[m].kinds)
        self._modalities += Counter()  # the modalities no model holds any more: gone
        del self.models[m], self.edges[m]
        self.changed.add(m)
        return neighbours

    def _link(self, a: Hashable, b: Hashable, weight: float) -> None:
        self.edges[a][b] = self.edges[b][a] = weight
        self.changed |= {a, b}

    def _unlink(self, a: Hashable, b: Hashable) -> None:
        del self.edges[a][b], self.edges[b][a]
        self.changed |= {a, b}

    def _make_cluster(self, members: set) -> None:
        name = min(members)
        self.members[name] = frozenset(members)
        union: Counter = Counter()
        for m in members:
            union.update(self.models[m].graph.elements)
            if self.cluster_of.get(m) != name:
                self.changed.add(m)
            self.cluster_of[m] = name
        self._union[name] = union
        self._index_add(union, name)
        if len(members) == 1:
            self.singletons.add(name)

    def _reshape_cluster(self, name: Hashable, members: set) -> None:
        """The cluster `name` with these members instead: the union and the index follow the
        models that left (all still known) and those that joined."""
        old = self.members[name]
        if old == members:
            return
        self.members[name] = frozenset(members)
        self.singletons.discard(name)
        if len(members) == 1:
            self.singletons.add(name)
        union, gone, new = self._union[name], [], []
        for m in old - members:
            for element in self.models[m].graph.elements:
                left = union[element] - 1
                if left:
                    union[element] = left
                else:
                    union.pop(element)  # (dict's own, in C: Counter's `del` is Python)
                    gone.append(element)
        for m in members - old:
            for element in self.models[m].graph.elements:
                count = union.get(element, 0)
                if not count:
                    new.append(element)
                union[element] = count + 1
            self.cluster_of[m] = name
            self.changed.add(m)
        self._index_discard(gone, name)
        self._index_add(new, name)

    def _drop_cluster(self, name: Hashable) -> None:
        self._index_discard(self._union.pop(name), name)
        del self.members[name]
        self.singletons.discard(name)

    def _index_add(self, elements: Iterable[str], name: Hashable) -> None:
        """The cluster's union holds these elements now (one call per model, not per element:
        a model has hundreds)."""
        index = self._index
        for element in elements:
            holders = index.get(element)
            if holders is None:
                index[element] = name
            elif type(holders) is set:
                holders.add(name)
            elif holders != name:
                index[element] = {holders, name}

    def _index_discard(self, elements: Iterable[str], name: Hashable) -> None:
        """The cluster's union holds these elements no more."""
        index = self._index
        for element in elements:
            holders = index[element]
            if type(holders) is not set:
                del index[element]  # (it was this cluster)
                continue
            holders.discard(name)
            if len(holders) == 1:
                index[element] = holders.pop()
