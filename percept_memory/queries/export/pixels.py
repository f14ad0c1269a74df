"""The pixels of a cluster: its crop, and its box and mask in the exported image.

A cluster's ImageROI gives a box in one of the scene's images, a crop of that box (maybe
rescaled, as the kitchen week's 64 px crops are) and a mask over the box or over the crop.
Masks are brought to the exported image's pixels here, once, for every format.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from percept_memory.converters.images import compress, png_compatible
from percept_memory.memory.types import Cluster, Image, ImageROI, Scene

Box = tuple[int, int, int, int]


@dataclass(frozen=True)
class Instance:
    """An object in an exported image: its box (x, y, width, height) and, when the cluster has
    a mask, the mask over the whole image (True where the object is)."""

    width: int
    height: int
    box: Box
    mask: np.ndarray | None


def scene_roi(cluster: Cluster, scene: Scene) -> ImageROI | None:
    """The cluster's first region in an image the scene has."""
    return next((h for h in cluster.hypotheses
                 if isinstance(h, ImageROI) and h.image in scene.images), None)


def crop_of(cluster: Cluster, scene: Scene) -> tuple[ImageROI, Image] | None:
    """The cluster's crop as stored, else cut from the scene image its box is in."""
    rois = [h for h in cluster.hypotheses if isinstance(h, ImageROI)]
    if stored := next((roi for roi in rois if roi.crop is not None), None):
        return stored, stored.crop
    if (roi := scene_roi(cluster, scene)) is None:
        return None
    image = scene.images[roi.image]
    x, y, w, h = clipped(roi.box, image.width, image.height)
    if not w or not h:
        return None
    return roi, Image(data=image.data[y:y + h, x:x + w], encoding=image.encoding)


def in_scene(roi: ImageROI, image: Image) -> Instance | None:
    """The ROI in its scene image (None if its box lies outside it)."""
    box = clipped(roi.box, image.width, image.height)
    if not box[2] or not box[3]:
        return None
    mask = None
    if roi.mask is not None:
        if roi.mask.data.shape[:2] == (image.height, image.width):
            mask = roi.mask.data > 0
        else:
            x, y, w, h = roi.box
            inside = np.zeros((image.height + h, image.width + w), bool)  # room for overhang
            inside[y:y + h, x:x + w] = _resized(roi.mask.data, w, h)
            mask = inside[:image.height, :image.width]
    return _instance(image, box, mask)


def in_crop(roi: ImageROI, crop: Image) -> Instance:
    """The ROI in its own crop: the whole crop, or its mask (scaled to the crop)."""
    mask = None if roi.mask is None else _resized(roi.mask.data, crop.width, crop.height)
    return _instance(crop, (0, 0, crop.width, crop.height), mask)


def _instance(image: Image, box: Box, mask: np.ndarray | None) -> Instance:
    """With a mask, the box is the mask's bounding box (as COCO has it)."""
    if mask is not None and mask.any():
        box = cv2.boundingRect(mask.astype(np.uint8))
    elif mask is not None:
        mask = None  # an empty mask says nothing: the box is the object
    return Instance(image.width, image.height, tuple(int(v) for v in box), mask)


def _resized(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    if mask.ndim == 3:
        mask = mask[..., 0]
    if mask.shape != (height, width):
        mask = cv2.resize(mask, (width, height), interpolation=cv2.INTER_NEAREST)
    return mask > 0


def clipped(box: Box, width: int, height: int) -> Box:
    x, y, w, h = box
    x0, y0 = min(max(x, 0), width), min(max(y, 0), height)
    x1, y1 = min(max(x + w, 0), width), min(max(y + h, 0), height)
    return x0, y0, x1 - x0, y1 - y0


def png(image: Image) -> bytes | None:
    """The image as PNG (None when PNG cannot hold it: float images)."""
    if not png_compatible(image.data):
        return None
    return compress(image.data, image.encoding, "png")


def rle(mask: np.ndarray) -> dict:
    """COCO's uncompressed run-length encoding: run lengths over the pixels in column-major
    order, starting with a run of background (pycocotools reads it with frPyObjects)."""
    flat = mask.ravel(order="F")
    starts = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.concatenate(([0], starts, [flat.size])))
    counts = ([0] if flat[0] else []) + runs.tolist()
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": counts}
