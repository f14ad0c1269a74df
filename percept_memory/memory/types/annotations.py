"""Annotations: what annotators say about an object hypothesis (thesis 3.2.3).

Adding a type is adding one class here (or anywhere) with `@stored_type`: storing, loading and
querying by its fields follow from its annotations. A class may also say
- `labels()`: the names it gives the object (searchable, used to name objects);
- `texts()`: free text to make searchable;
- `views()`: the view descriptors it gives the object's graph of views, words of the type's own
  dictionary (the long-term catalogue, memory/catalogue/, Duceux 5.3);
- `similarity(a, b)`: how alike two observations look by this kind of evidence, in [0, 1]
  (identity resolution combines the kinds two observations share, thesis 6.1.2); or, faster,
  `similarities(a, b)` for two lists at once, a matrix (the built-in types: compare.py);
- `descriptors()`: the same evidence as named unit vectors, for similarity search
  (appearance.py says how; memory/similarity.py indexes them).
"""

from __future__ import annotations

import functools
import hashlib
from typing import Annotated, ClassVar, Literal

import numpy as np
from bson import ObjectId
from pydantic import AliasChoices, Field

from . import compare
from .appearance import sqrt_distribution, unit
from .base import Id, Identifiable, Model, Name, Timestamp, stored_type
from .raw import Box, Finite, NDArray, Pose, Vec3

Probability = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
Distance = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]  # metres, >= 0


class Annotation(Identifiable):
    """Base of all annotations. `source` names the annotator that produced it.

    `naming_weight` says how much the type's labels name the object (thesis 5.4.5: names from
    word statistics): a product or a logo names it, a shape or a colour only describes it."""

    source: Name = ""
    naming_weight: ClassVar[float] = 0.0
    label_fields: ClassVar[tuple[str, ...]] = ()
    """The fields whose values are the type's labels, when it gives them unconditionally: an
    exact predicate on one (classification:class_name=cereal) is then looked up by label."""

    def labels(self) -> list[str]:
        return [value for name in self.label_fields if (value := getattr(self, name))]

    def texts(self) -> list[str]:
        return []

    def views(self) -> list[str]:
        """None by default: where an object is, or who tracked it, is not what it looks like."""
        return []

    @staticmethod
    def similarity(a: Annotation, b: Annotation) -> float | None:
        """None: this kind of annotation says nothing about whether two observations match."""
        return None

    def descriptors(self) -> dict[str, np.ndarray]:
        """Name -> unit vector: what similarity search finds look-alikes by (none here)."""
        return {}


def _read_only(vector: np.ndarray | None) -> np.ndarray | None:
    """A vector kept with the annotation, shared by whoever asks: nobody may change it."""
    if vector is not None:
        vector.setflags(write=False)
    return vector


@stored_type("pm.annotation.Location")
class Location(Annotation):
    """Where the object is: the region of interest it was found in (e.g. counter_top_sink),
    its position in the map frame, and how it relates to the region ("on"). `position_sigma`:
    the standard deviation of the position's noise along x, y and z in metres, as the
    perception knows it (localisation and segmentation); identity then knows how far apart
    two observations of one object may lie, instead of only learning it from its decisions."""

    region: Name | None = None
    position: Vec3 | None = None
    position_sigma: tuple[Distance, Distance, Distance] | None = None
    frame: Name = "map"
    relation: Name | None = None
    pose: Pose | None = None  # pose relative to the region's frame, when known


@stored_type("pm.annotation.Classification", aliases=("rs.annotation.Classification",))
class Classification(Annotation):
    """A classifier's verdict, with the per-class confidences when it gives them."""

    naming_weight: ClassVar[float] = 1.0
    label_fields: ClassVar[tuple[str, ...]] = ("class_name",)

    class_name: Name = Field(validation_alias=AliasChoices("class_name", "classname"))
    confidence: Probability | None = None
    classifier: Name = ""
    feature: Name = Field(default="", validation_alias=AliasChoices("feature", "featurename"))
    confidences: dict[Name, Finite] = {}

    def views(self) -> list[str]:
        return [self.class_name]

    @staticmethod
    def similarities(a: list[Classification], b: list[Classification]) -> np.ndarray:
        """The overlap of the per-class confidences where both give them, else whether the
        verdicts are the same class."""
        out = compare.same_labels([x.class_name for x in a], [y.class_name for y in b])
        both = np.array([bool(x.confidences) for x in a])[:, None] & np.array(
            [bool(y.confidences) for y in b])[None, :]
        if both.any():
            overlap = compare.bhattacharyya([x.confidences for x in a],
                                            [y.confidences for y in b])
            out = np.where(both, overlap, out)
        return out


@stored_type("pm.annotation.Detection", aliases=("rs.annotation.Detection",))
class Detection(Annotation):
    """A detector found a known object (by name) in the hypothesis."""

    naming_weight: ClassVar[float] = 1.0
    label_fields: ClassVar[tuple[str, ...]] = ("name",)

    name: Name
    confidence: Probability | None = None
    box: Box | None = None

    def views(self) -> list[str]:
        return [self.name]

    @staticmethod
    def similarities(a: list[Detection], b: list[Detection]) -> np.ndarray:
        return compare.same_labels([x.name for x in a], [y.name for y in b])


@stored_type("pm.annotation.Shape", aliases=("rs.annotation.Shape",))
class Shape(Annotation):
    """A primitive shape: box, cylinder, sphere, flat, ..."""

    label_fields: ClassVar[tuple[str, ...]] = ("shape",)

    shape: Name
    confidence: Probability | None = None

    def views(self) -> list[str]:
        return [self.shape]

    @staticmethod
    def similarities(a: list[Shape], b: list[Shape]) -> np.ndarray:
        return compare.same_labels([x.shape for x in a], [y.shape for y in b])


@stored_type("pm.annotation.SemanticColor")
class SemanticColor(Annotation):
    """Named colours with the share of the object's pixels each covers."""

    ratios: dict[Name, Annotated[float, Field(ge=0.0, le=1.0)]]

    def labels(self) -> list[str]:
        return [name for name, share in self.ratios.items() if share >= 0.2]

    def views(self) -> list[str]:
        return self.labels()

    @staticmethod
    def similarities(a: list[SemanticColor], b: list[SemanticColor]) -> np.ndarray:
        return compare.shared_share([x.ratios for x in a], [y.ratios for y in b])


@stored_type("pm.annotation.ColorHistogram")
class ColorHistogram(Annotation):
    """A colour histogram of the object's pixels (e.g. 16 x 16 hue-saturation bins)."""

    histogram: NDArray
    space: Name = "HS"

    def views(self) -> list[str]:
        """Its three fullest bins: a coarse word that the same side of an object repeats."""
        return compare.top_bins(self.histogram, 3, self.space)

    @functools.cached_property
    def roots(self) -> np.ndarray | None:
        """The square roots of the normalised histogram, made once: identity compares a
        remembered object's evidence with every scene's (evidence is never changed)."""
        return _read_only(sqrt_distribution(self.histogram))

    @staticmethod
    def similarities(a: list[ColorHistogram], b: list[ColorHistogram]) -> np.ndarray:
        """Bhattacharyya overlap of every pair at once (sqrt p . sqrt q of the normalised
        histograms): identity compares every new observation with every candidate."""
        return compare.pairwise(a, b, lambda h: (h.space, h.histogram.shape),
                                lambda h: h.roots, lambda p, q: np.minimum(p @ q.T, 1.0))

    def descriptors(self) -> dict[str, np.ndarray]:
        """The same square roots, so search ranks by the same overlap (per space and size)."""
        vector = self.roots
        return {} if vector is None else {
            f"histogram-{self.space}-{vector.size}": vector}


@stored_type("pm.annotation.FeatureVector")
class FeatureVector(Annotation):
    """A named descriptor: VFH (308 floats), CNN features, ..."""

    name: Name
    vector: NDArray

    def views(self) -> list[str]:
        return compare.visual_words(self.name, self.vector)

    @functools.cached_property
    def direction(self) -> np.ndarray | None:
        """The vector scaled to length 1, made once (as ColorHistogram.roots)."""
        return _read_only(unit(self.vector))

    @staticmethod
    def similarities(a: list[FeatureVector], b: list[FeatureVector]) -> np.ndarray:
        """Cosine of every pair at once (0 for opposite directions)."""
        return compare.pairwise(a, b, lambda f: (f.name, f.vector.shape),
                                lambda f: f.direction, lambda u, v: np.clip(u @ v.T, 0.0, 1.0))

    def descriptors(self) -> dict[str, np.ndarray]:
        """The direction, so search ranks by the same cosine (per name and length)."""
        vector = self.direction
        return {} if vector is None else {f"feature-{self.name}-{vector.size}": vector}


@stored_type("pm.annotation.Text")
class Text(Annotation):
    """Text read on the object (OCR)."""

    text: str
    confidence: Probability | None = None
    box: Box | None = None
    language: str | None = None

    def texts(self) -> list[str]:
        return [self.text]

    def views(self) -> list[str]:
        return sorted(compare.words(self.text))

    @staticmethod
    def similarities(a: list[Text], b: list[Text]) -> np.ndarray:
        return compare.shared_words([x.text for x in a], [y.text for y in b])


@stored_type("pm.annotation.Logo")
class Logo(Annotation):
    """A brand logo recognised on the object."""

    naming_weight: ClassVar[float] = 1.5
    label_fields: ClassVar[tuple[str, ...]] = ("brand",)

    brand: Name
    confidence: Probability | None = None
    box: Box | None = None

    def views(self) -> list[str]:
        return [self.brand]

    @staticmethod
    def similarities(a: list[Logo], b: list[Logo]) -> np.ndarray:
        return compare.same_labels([x.brand for x in a], [y.brand for y in b])


ProductValue = str | bool | int | float


@stored_type("pm.annotation.Product")
class Product(Annotation):
    """A product matched in a registry: name, brand and free key-values (category, weight,
    ingredients, perishability, ...)."""

    naming_weight: ClassVar[float] = 2.0
    label_fields: ClassVar[tuple[str, ...]] = ("name", "brand")

    name: Name | None = None
    brand: Name | None = None
    properties: dict[str, ProductValue] = {}

    def views(self) -> list[str]:
        return self.labels()

    def texts(self) -> list[str]:
        return [f"{key} {value}" for key, value in self.properties.items()]

    @staticmethod
    def similarities(a: list[Product], b: list[Product]) -> np.ndarray:
        return compare.same_labels([x.name for x in a], [y.name for y in b])


@stored_type("pm.annotation.Barcode")
class Barcode(Annotation):
    """A barcode read on the object."""

    label_fields: ClassVar[tuple[str, ...]] = ("code",)

    code: str
    symbology: Name = ""

    def views(self) -> list[str]:
        return [self.code]

    @staticmethod
    def similarities(a: list[Barcode], b: list[Barcode]) -> np.ndarray:
        return compare.same_labels([x.code for x in a], [y.code for y in b])


@stored_type("pm.lookup.Provenance")
class LookupProvenance(Model):
    """Where a lookup result came from: the backend, fresh from it or reused from the
    perceptual-hash cache (with the Hamming distance of the two crops' hashes), how long getting
    it took, and the enrichment job that appended it."""

    backend: Name
    cached: bool = False
    hash_distance: Annotated[int, Field(ge=0, le=64)] = 0
    latency_ms: Annotated[float, Field(ge=0)] = 0.0
    job_id: Id | None = None


def lookup_annotation_id(job_id: ObjectId, position: int) -> ObjectId:
    """The id of the `position`-th annotation a lookup job appends: the same on every run (a
    rerun appends nothing new), and naming finds the job's provenance from it."""
    digest = hashlib.blake2b(job_id.binary + position.to_bytes(4, "big"), digest_size=8)
    return ObjectId(job_id.binary[:4] + digest.digest())


@stored_type("pm.annotation.WebLookup", aliases=("rs.annotation.Goggles",))
class WebLookup(Annotation):
    """One result of a web image lookup (thesis 5.4): a category (text, logo, product, similar
    image, ...), its title, the matched region and links; `provenance` when an enrichment
    worker appended it."""

    naming_weight: ClassVar[float] = 1.0

    service: Name = ""
    category: str
    title: str
    box: Box | None = None
    links: list[str] = []
    provenance: LookupProvenance | None = None

    def labels(self) -> list[str]:
        return [self.title] if self.category in ("logo", "product") else []

    def texts(self) -> list[str]:
        return [self.title]


@stored_type("pm.annotation.Tracking")
class Tracking(Annotation):
    """A tracking id given by a tracker (thesis 6.5); `source` names the tracker."""

    tracking_id: int = Field(validation_alias=AliasChoices("tracking_id", "trackingID"))


@stored_type("pm.annotation.GroundTruth")
class GroundTruth(Annotation):
    """The true class (and pose) of the object, from a labelled data set: it names the object
    more surely than any annotator."""

    naming_weight: ClassVar[float] = 5.0
    label_fields: ClassVar[tuple[str, ...]] = ("class_name",)

    class_name: Name
    pose: Pose | None = None


@stored_type("pm.annotation.Geometry")
class Geometry(Annotation):
    """Size and pose of the object's bounding box."""

    size: Vec3 | None = None  # width, depth, height in metres
    volume: Annotated[float, Field(ge=0)] | None = None
    pose: Pose | None = None
    distance_to_plane: Finite | None = None
    semantic_size: Name | None = None

    def labels(self) -> list[str]:
        return [self.semantic_size] if self.semantic_size else []


@stored_type("pm.annotation.Relation")
class Relation(Annotation):
    """A row of the scene's relations table (thesis table 3.1): `predicate(a, b)` holds with
    `probability`; `b` is None for unary predicates."""

    predicate: Name
    a: Name
    b: Name | None = None
    probability: Probability = 1.0


@stored_type("pm.annotation.LogLine")
class LogLine(Annotation):
    """A line of the scene's log: which annotator (`source`) said what, when, how long it took."""

    message: str
    level: Literal["debug", "info", "warning", "error"] = "info"
    time: Timestamp | None = None
    duration_ms: Annotated[float, Field(ge=0)] | None = None
