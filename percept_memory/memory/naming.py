"""What an object is called: the names its observations' annotations give it, each weighted by
the evidence for it (thesis 5.4.5: word statistics), so "the ketchup" finds the object a Heinz
logo and a "ketchup" classification were seen on.

How much an annotation's name counts:
- its type: a product or a logo names an object, a shape or a colour only describes it, a
  ground truth names it for sure (`naming_weight`);
- its confidence, when the annotator gives one (a classifier's verdict);
- whether it is a web lookup's answer (a WebLookup, or what a lookup job appended beside it):
  weak evidence, for the service answers with whatever product the crop resembles, and weaker
  the further the crop's perceptual hash was from the one the cached answer was given for;
- a person's correction (types/curation.py): the one in force decides what its observation
  names, whatever the annotators said (a rejected detection names nothing), with a weight
  no number of annotators' observations reaches;
- agreement: per observation, each annotator (`source`) counts with diminishing returns (its
  strongest say fully, the next half, the next a quarter...), so two annotators agreeing
  outweigh one saying the same name in several annotations.

An object's `label_weights` are a sum over its observations, each term and each sum rounded to
DECIMALS: decimal sums are exact, so they come out the same whatever order the observations and
the annotations appended to them later (web lookups) arrive in, and the belief built live
equals the one rebuilt from the stored scenes.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping

from percept_memory.converters import escape_key, unescape_key

from .search_keys import normal_label
from .types import Annotation, Rejection, WebLookup
from .types.annotations import lookup_annotation_id
from .types.curation import in_force, verdict

NAMES_KEPT = 3
DECIMALS = 6
LOOKUP_TRUST = 0.15  # a lookup's annotation counts this much of what another annotator's would
# (a product and a logo of the same brand then add up to less than a classifier's 0.5)
HALVING_BITS = 4  # ... and half that for every 4 bits between the crop's hash and the cached one


def naming_labels(annotations: Iterable) -> Counter:
    """The names one observation's annotations give their object, with their weights."""
    annotations = [a for a in in_force(annotations) if isinstance(a, Annotation)]
    if (decided := verdict(annotations)) is not None:
        if isinstance(decided, Rejection) or not (name := normal_label(decided.class_name)):
            return Counter()
        return Counter({name: round(decided.naming_weight, DECIMALS)})
    distances = _lookup_distances(annotations)
    said: dict[str, dict[str, list[float]]] = {}  # name -> source -> weights
    for annotation in annotations:
        weight = reliability(annotation, distances.get(annotation.id))
        if weight <= 0:
            continue
        for label in annotation.labels():
            if name := normal_label(label):
                said.setdefault(name, {}).setdefault(annotation.source, []).append(weight)
    return Counter({name: round(sum(map(_diminishing, by_source.values())), DECIMALS)
                    for name, by_source in said.items()})


def reliability(annotation: Annotation, lookup_distance: int | None = None) -> float:
    """How much a name this annotation gives counts; `lookup_distance`: the hash distance of
    the lookup answer it was appended from, None when it is not a lookup's."""
    weight = annotation.naming_weight
    confidence = getattr(annotation, "confidence", None)
    if confidence is not None:
        weight *= confidence
    if isinstance(annotation, WebLookup):  # the answer itself: its provenance says how near
        lookup_distance = annotation.provenance.hash_distance if annotation.provenance else 0
    if lookup_distance is not None:
        weight *= LOOKUP_TRUST * 0.5 ** (lookup_distance / HALVING_BITS)
    return weight


def _lookup_distances(annotations: list[Annotation]) -> dict:
    """Annotation id -> hash distance of the lookup answer, for the annotations a lookup job
    appended beside its WebLookups (their ids derive from the job, lookups.py)."""
    jobs = {a.provenance.job_id: a.provenance.hash_distance for a in annotations
            if isinstance(a, WebLookup) and a.provenance and a.provenance.job_id}
    return {lookup_annotation_id(job, position): distance for job, distance in jobs.items()
            for position in range(len(annotations))}


def _diminishing(weights: list[float]) -> float:
    """One annotator's say on a name: its strongest weight, half the next, a quarter..."""
    return sum(w / 2**i for i, w in enumerate(sorted(weights, reverse=True)))


def stored_weights(object_doc: Mapping) -> Counter:
    return Counter({unescape_key(k): v for k, v in object_doc.get("label_weights", {}).items()})


def naming_fields(weights: Counter) -> dict:
    """The object's name fields from its label weights: the heaviest names first (ties in
    alphabetical order, so that the order of arrival never decides)."""
    rounded = {label: round(weight, DECIMALS) for label, weight in weights.items()}
    kept = {label: weight for label, weight in rounded.items() if weight > 0}
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
