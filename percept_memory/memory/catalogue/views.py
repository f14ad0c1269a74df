"""The view descriptors of one observation: the words its evidence declares (each type's
`views()`, in its own class), as nodes of the graph of views "modality:word" where the modality
is the type (Duceux 5.3.2: one dictionary per descriptor type)."""

from __future__ import annotations

from collections.abc import Iterable

from .graph_of_views import node


def observation_views(evidence: Iterable) -> list[str]:
    """The nodes of an observation's evidence: identity's (consolidation.py), the evidence
    a cluster arrived with, so what enrichment appended later never changes the catalogue and
    a rebuild learns what the live path did."""
    return sorted({node(type(item).__name__.lower(), word) for item in evidence
                   for word in getattr(item, "views", list)()})
