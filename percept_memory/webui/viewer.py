"""The scene viewer (issue 17): what the scene page draws over each camera image, as SVG, so
that it reads without JavaScript. Per cluster whose image region lies on the image: its box,
its mask's outline, and the box of every annotation that has one (a Detection's, a Text's,
a web lookup's: a `box` field, in image pixels), each shape tagged with its layer (region,
mask or the annotation's type) and annotator, which static/viewer.js switches on and off; the
cluster's number, and its labels, shown on hover and focus by CSS. Depth images carry their
range for the false-colour legend (images.false_colour)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from bson import ObjectId

from percept_memory.memory.types import Annotation, Cluster, Image, ImageROI, Scene

from .images import depth_range, is_depth
from .layout import CHAR_WIDTH
from .render import type_name

BOX, MASK = "region", "mask"  # the layers of the cluster's own region
OUTLINE_TOLERANCE = 1.0  # px: a mask outline may stray this far from the mask's edge


@dataclass
class Shape:
    layer: str  # BOX, MASK or an annotation type's name
    annotator: str  # "" for the cluster's own region
    box: tuple[int, int, int, int]
    outline: str = ""  # SVG path data of a mask, in image pixels


@dataclass
class Tip:
    """The label shown on hover: its text and the box behind it, above the cluster's box
    (below it at the image's top edge), within the image."""

    text: str
    x: float
    y: float
    width: float
    height: float


@dataclass
class Mark:
    """One cluster on the image: a link to its page around its shapes."""

    number: int
    cluster_id: ObjectId
    shapes: list[Shape]
    tip: Tip  # the object's name and the labels annotators gave


@dataclass
class Overlay:
    name: str
    image: Image
    marks: list[Mark] = field(default_factory=list)
    depth: tuple[float, float] | None = None  # nearest and farthest reading, in metres

    @property
    def layers(self) -> list[str]:
        return _distinct(s.layer for m in self.marks for s in m.shapes)

    @property
    def annotators(self) -> list[str]:
        return _distinct(s.annotator for m in self.marks for s in m.shapes if s.annotator)

    @property
    def font(self) -> float:
        return _font(self.image)


def overlays(scene: Scene, names: dict) -> list[Overlay]:
    """The scene's images in order, each with the clusters drawn on it (numbered from 1 in
    cluster order, as on the page); `names` maps object ids to their names."""
    shown = {name: Overlay(name, image, depth=_metres(image) if is_depth(image) else None)
             for name, image in scene.images.items()}
    for number, cluster in enumerate(scene.clusters, 1):
        roi = cluster.hypothesis_of(ImageROI)
        if roi is not None and roi.image in shown:
            overlay = shown[roi.image]
            overlay.marks.append(_mark(number, cluster, roi, names, overlay.image))
    return list(shown.values())


def _mark(number: int, cluster: Cluster, roi: ImageROI, names: dict, image: Image) -> Mark:
    shapes = [Shape(BOX, "", roi.box)]
    if roi.mask is not None:
        shapes.append(Shape(MASK, "", roi.box, outline(roi.mask.data, roi.box)))
    annotations = [a for a in cluster.annotations if isinstance(a, Annotation)]
    shapes += [Shape(type_name(a), a.source, tuple(a.box)) for a in annotations
               if getattr(a, "box", None) is not None]
    labels = ", ".join(_distinct(label for a in annotations for label in a.labels()))
    said = ": ".join(filter(None, [names.get(cluster.object_id), labels])) or "no labels"
    return Mark(number, cluster.id, shapes, _tip(f"{number}. {said}", roi.box, image))


def _tip(text: str, box: tuple[int, int, int, int], image: Image) -> Tip:
    font = _font(image)
    width, height = len(text) * font * CHAR_WIDTH + font, font * 1.5
    above = box[1] - height - 2
    y = above if above >= 0 else min(box[1] + box[3] + 2, image.height - height)
    return Tip(text, max(0.0, min(box[0], image.width - width)), y, width, height)


def _font(image: Image) -> float:
    """Label size in image pixels: readable at the size the page shows the image."""
    return max(10.0, image.width / 56)


def outline(mask: np.ndarray, box: tuple[int, int, int, int]) -> str:
    """The mask's outer contours as SVG path data, placed on its box (a mask may have been
    stored at another size than its box)."""
    x, y, width, height = box
    plane = mask if mask.ndim == 2 else mask[..., 0]
    contours, _ = cv2.findContours((plane > 0).astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)
    sx, sy = width / plane.shape[1], height / plane.shape[0]
    paths = []
    for contour in contours:
        points = cv2.approxPolyDP(contour, OUTLINE_TOLERANCE, True)[:, 0]
        if len(points) >= 3:
            paths.append("M" + " L".join(f"{x + px * sx:.1f} {y + py * sy:.1f}"
                                         for px, py in points) + " Z")
    return " ".join(paths)


def _metres(image: Image) -> tuple[float, float] | None:
    """A depth image's range in metres: integer depth is in millimetres (ROS' 16UC1)."""
    span = depth_range(image.data)
    scale = 1000.0 if span is not None and image.data.dtype.kind in "iu" else 1.0
    return span and (span[0] / scale, span[1] / scale)


def _distinct(items) -> list:
    return list(dict.fromkeys(items))
