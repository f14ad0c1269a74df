"""The view descriptors of one observation: the words its evidence declares (each type's
`views()`, in its own class), as nodes of the graph of views "modality:word" where the modality
is the type (Duceux 5.3.2: one dictionary per descriptor type), and the ORB visual words of its
crop (types/visual_words.py: computed here, a function of the crop that arrived)."""

from __future__ import annotations

from ..types import Cluster, ImageROI
from ..types.visual_words import VisualWords
from .graph_of_views import node


def observation_views(cluster: Cluster, arrived: int) -> list[str]:
    """The nodes of a cluster's evidence as it arrived (`arrived` annotations: what enrichment
    appended later never changes the catalogue, so a rebuild learns what the live path did)."""
    evidence = [*cluster.hypotheses, *cluster.annotations[:arrived], *crop_words(cluster)]
    return sorted({node(type(item).__name__.lower(), word) for item in evidence
                   for word in getattr(item, "views", list)()})


def crop_words(cluster: Cluster) -> list[VisualWords]:
    """The visual words of the cluster's crops (none for a crop without keypoints)."""
    found = (VisualWords.of_crop(h.crop.data, None if h.mask is None else h.mask.data)
             for h in cluster.hypotheses if isinstance(h, ImageROI) and h.crop is not None)
    return [words for words in found if words is not None]
