"""JSONL: `features.jsonl`, one line per cluster: its id, label and feature vectors by name
(FeatureVector annotations such as VFH or Caffe CNN features, and the colour histogram as
`color_histogram`), each flattened to a list of numbers."""

from __future__ import annotations

from percept_memory.memory.types import Cluster, ColorHistogram, FeatureVector

from .archive import Spool
from .writer import Item, Writer

HISTOGRAM = "color_histogram"


class Jsonl(Writer):
    def __init__(self, *args):
        super().__init__(*args)
        self.lines = Spool()

    def add(self, items: list[Item]) -> None:
        wanted = set(self.query.feature)
        for item in items:
            found = {name: vector for name, vector in features(item.cluster)
                     if not wanted or name in wanted}
            if not found:
                self.skip("no feature vector" + (f" named {', '.join(sorted(wanted))}"
                                                 if wanted else ""))
                continue
            self.class_id(item.label)
            self.lines.line({"cluster_id": str(item.cluster.id), "label": item.label.name,
                             "features": found})
            self.exported(item, {"line": self.lines.items})

    def finish(self) -> None:
        self.archive.add("features.jsonl", self.lines.chunks(), self.lines.size)
        super().finish()


def features(cluster: Cluster):
    """(name, numbers) of the cluster's feature vectors, the first of each name."""
    seen = set()
    for annotation in cluster.annotations:
        if isinstance(annotation, FeatureVector):
            name, vector = annotation.name, annotation.vector
        elif isinstance(annotation, ColorHistogram):
            name, vector = HISTOGRAM, annotation.histogram
        else:
            continue
        if name not in seen:
            seen.add(name)
            yield name, vector.astype(float).ravel().tolist()
