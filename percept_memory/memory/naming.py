"""What an object is called: the words its observations' annotations name it by, each weighted
by how much its type names rather than describes an object (thesis 5.4.5: word statistics), so
"the ketchup" finds the object a Heinz logo and a "ketchup" classification were seen on.

An object's `label_weights` are a sum over its observations, so they come out the same
whatever order the observations and the annotations appended to them later (web lookups)
arrive in: the belief built live equals the one rebuilt from the stored scenes.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping

from percept_memory.converters import escape_key, unescape_key

from .types import Annotation

NAMES_KEPT = 3


def naming_labels(annotations: Iterable) -> Counter:
    """The words annotations name their object by, with their weights."""
    found: Counter = Counter()
    for annotation in annotations:
        if isinstance(annotation, Annotation) and annotation.naming_weight:
            for label in annotation.labels():
                if label and label.strip():
                    found[label.strip().casefold()] += annotation.naming_weight
    return found


def stored_weights(object_doc: Mapping) -> Counter:
    return Counter({unescape_key(k): v for k, v in object_doc.get("label_weights", {}).items()})


def naming_fields(weights: Counter) -> dict:
    """The object's name fields from its label weights: the heaviest names first (ties in
    alphabetical order, so that the order of arrival never decides)."""
    kept = {label: weight for label, weight in weights.items() if weight > 1e-9}
    names = sorted(kept, key=lambda label: (-kept[label], label))[:NAMES_KEPT]
    return {"names": names, "name": names[0] if names else None,
            "label_weights": {escape_key(k): v for k, v in sorted(kept.items())}}


def renamed(object_doc: Mapping, before: Iterable, after: Iterable) -> dict | None:
    """The update of an object's names when one of its observations' annotations changed from
    `before` to `after` (annotations appended by enrichment); None when the names are the same."""
    gained, lost = naming_labels(after), naming_labels(before)
    if gained == lost:
        return None
    weights = stored_weights(object_doc)
    weights.update(gained)
    weights.subtract(lost)
    return {"$set": naming_fields(weights)}
