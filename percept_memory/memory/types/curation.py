"""What a person says about a cluster: corrections of what the annotators said (issue 21).

A correction is an annotation of its own, appended beside the annotators' (which it never
changes), carrying who made it and when. The latest correction in force decides:
- `Relabel`: the object seen here is `class_name` (the class, or the name);
- `Rejection`: this detection is wrong, there is no object here;
- `SameObject`: the object seen here is the one seen in another, earlier cluster (two
  objects the memory holds apart are one: they are merged);
- `DifferentObject`: the clusters split off show another object than the rest of the
  object's observations (one object the memory made of two is split: identity keeps the two
  sides apart);
- `Undo`: takes back an earlier correction; itself recorded, so the audit keeps both.

Which correction is in force depends on the set of annotations, never on the order they were
appended in (the latest by time, then id), so the belief built live equals the one rebuilt.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Annotated, ClassVar

from pydantic import AfterValidator, Field, StringConstraints

from .annotations import Annotation
from .base import MAX_NAME, Id, Timestamp, no_controls, stored_type

HUMAN = "human"  # the `source` of every correction: the annotator is a person
Author = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=100),
                   AfterValidator(no_controls)]
Label = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1,
                                         max_length=MAX_NAME), AfterValidator(no_controls)]


class Correction(Annotation):
    """Base of what a person says: who (`author`) and when (`time`, ns)."""

    source: str = HUMAN
    author: Author
    time: Timestamp


@stored_type("pm.annotation.Relabel")
class Relabel(Correction):
    """A person's class or name for the object seen here: it names the object more surely than
    any annotator, and than any number of them (naming.py)."""

    naming_weight: ClassVar[float] = 1_000_000.0

    class_name: Label

    def labels(self) -> list[str]:
        return [self.class_name]


@stored_type("pm.annotation.Rejection")
class Rejection(Correction):
    """A person says this detection is wrong: no object is here. Identity leaves the cluster
    out, and exports skip it."""

    reason: Annotated[str, Field(max_length=500)] = ""


@stored_type("pm.annotation.SameObject")
class SameObject(Correction):
    """A person says the object seen here is the one seen in the cluster `other`, an earlier
    observation of the same map: identity merges the two objects when it reaches this one."""

    other: Id


@stored_type("pm.annotation.DifferentObject")
class DifferentObject(Correction):
    """A person says the clusters `split_off` (this one among them) show another object than
    the clusters `apart_from` (the rest of the observations of the object they were all taken
    for): identity never takes a cluster of one side for an object a cluster of the other side
    was taken for, nor merges two such objects. One correction for the whole split, stored on
    the earliest cluster split off, so one undo takes it back."""

    split_off: Annotated[list[Id], Field(min_length=1)]
    apart_from: Annotated[list[Id], Field(min_length=1)]

    def sides(self) -> tuple[frozenset, frozenset]:
        return frozenset(self.split_off), frozenset(self.apart_from)


@stored_type("pm.annotation.Undo")
class Undo(Correction):
    """A person takes back the correction `undoes` (a Relabel, a Rejection, a SameObject, a
    DifferentObject)."""

    undoes: Id


def in_force(annotations: Iterable) -> list:
    """The annotations minus the undos and the corrections they took back."""
    annotations = list(annotations)
    undone = {a.undoes for a in annotations if isinstance(a, Undo)}
    return [a for a in annotations
            if not isinstance(a, Undo) and getattr(a, "id", None) not in undone]


def verdict(annotations: Iterable) -> Relabel | Rejection | None:
    """The correction that decides, of those in force: the latest (by time, then id)."""
    said = [a for a in in_force(annotations) if isinstance(a, Relabel | Rejection)]
    return max(said, key=lambda a: (a.time, a.id), default=None)


def rejected(annotations: Iterable) -> bool:
    """Whether a person said the detection these annotations are of is wrong."""
    return isinstance(verdict(annotations), Rejection)


def same_as(annotations: Iterable) -> list:
    """The earlier clusters a person said show the same object as these annotations' cluster."""
    return sorted({a.other for a in in_force(annotations) if isinstance(a, SameObject)})


def splits(annotations: Iterable) -> list[DifferentObject]:
    """The splits in force that these annotations hold."""
    return [a for a in in_force(annotations) if isinstance(a, DifferentObject)]


def identity_said(annotations: Iterable) -> tuple[bool, list, set]:
    """What people said that identity decides on: whether the cluster is no object at all,
    which earlier clusters show its object, and which observations it keeps apart (the
    splits it holds). A correction that changes it rebuilds the map's belief
    (memory/curation.py)."""
    annotations = list(annotations)
    return rejected(annotations), same_as(annotations), {s.sides() for s in splits(annotations)}
