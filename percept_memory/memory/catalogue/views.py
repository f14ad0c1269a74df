"""The view descriptors of one observation: the words its evidence declares (each type's
`views()`, in its own class), as nodes of the graph of views "modality:word" where the modality
is the type (Duceux 5.3.2: one dictionary per descriptor type)."""

from __future__ import annotations

from ..types import Cluster
from .graph_of_views import node


def observation_views(cluster: Cluster, arrived: int) -> list[str]:
    """The nodes of a cluster's evidence as it arrived (`arrived` annotations: what enrichment
    appended later never changes the catalogue, so a rebuild learns what the live path did)."""
    evidence = [*cluster.hypotheses, *cluster.annotations[:arrived]]
    return sorted({node(type(item).__name__.lower(), word) for item in evidence
                   for word in getattr(item, "views", list)()})
