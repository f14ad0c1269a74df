"""Labels from the chosen source, with who gave them: the provenance of a training label.

classification, detection, ground_truth and text take the most confident annotation of that
type (the first of equally confident ones); object takes the name the belief state gives the
object the cluster is believed to be (named from the words of all its observations).
A person's correction in force (memory/types/curation.py) overrides every source but text:
its label is the corrected one (by object, in the letters of the object's name when the two
are one name: names are stored normalised), its annotator `human:<author>`, and it says it is
`corrected`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from bson import ObjectId

from percept_memory.memory.search_keys import normal_label
from percept_memory.memory.types import (
    Annotation,
    Classification,
    Cluster,
    Detection,
    GroundTruth,
    Relabel,
    Text,
)
from percept_memory.memory.types.curation import HUMAN, verdict

from .model import LabelSource

BELIEF = "belief state"  # the annotator of object names: identity resolution


@dataclass(frozen=True)
class Label:
    name: str
    annotator: str  # the annotation's source, or BELIEF for an object's name
    annotation_id: ObjectId | None = None
    corrected: bool = False  # a person's correction, not what the source said


ANNOTATIONS: dict[str, tuple[type[Annotation], str]] = {
    "classification": (Classification, "class_name"),
    "detection": (Detection, "name"),
    "ground_truth": (GroundTruth, "class_name"),
    "text": (Text, "text"),
}


def label_of(cluster: Cluster, source: LabelSource,
             object_names: Mapping[ObjectId, str]) -> Label | None:
    """The cluster's label from `source`, or None when that source says nothing about it."""
    name = object_names.get(cluster.object_id) if source == "object" else None
    if source != "text" and isinstance(decided := verdict(cluster.annotations), Relabel):
        # by object, one object is one class: the correction its name, in the name's letters
        same = name is not None and normal_label(name) == normal_label(decided.class_name)
        return Label(name if same else decided.class_name, f"{HUMAN}:{decided.author}",
                     decided.id, True)
    if source == "object":
        return Label(name, BELIEF) if name else None
    kind, field = ANNOTATIONS[source]
    named = [a for a in cluster.annotations_of(kind) if getattr(a, field).strip()]
    if not named:
        return None
    best = max(named, key=_confidence)
    return Label(getattr(best, field).strip(), best.source, best.id)


def _confidence(annotation: Annotation) -> float:
    confidence = getattr(annotation, "confidence", None)
    return -1.0 if confidence is None else confidence
