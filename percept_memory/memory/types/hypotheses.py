"""Object hypotheses (thesis 3.2.2): where in the data an object might be."""

from __future__ import annotations

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from . import compare
from .appearance import crop_descriptors, hash_bits
from .base import Model, Name, stored_type
from .json_forms import image_limit
from .raw import Box, Finite, Image, NDArray, PointCloud, Vec3, check_pixels


class Hypothesis(Model):
    """Base of the ways to say "there may be an object here"."""

    def views(self) -> list[str]:
        """View descriptors of the object's look (annotations.Annotation.views): none here."""
        return []

    def descriptors(self) -> dict[str, np.ndarray]:
        """Name -> unit vector, as Annotation.descriptors (none here)."""
        return {}

PHASH_PATTERN = "^[0-9a-f]{16}$"
PHASH_SIGMA_BITS = 6.5  # g(4 bits) = 0.91, g(12) = 0.43, g(28) = 0.01


@stored_type("pm.hypothesis.ImageROI")
class ImageROI(Hypothesis):
    """A region of a scene image, with its mask, the cropped pixels and their perceptual hash
    (64-bit pHash as 16 hex digits) for fast appearance comparison."""

    box: Box
    image: Name = "color"  # which of the scene's images the box refers to
    mask: Image | None = None
    crop: Image | None = None
    phash: str | None = Field(default=None, pattern=PHASH_PATTERN)

    @field_validator("crop")
    @classmethod
    def _small_crop(cls, crop: Image | None, info: ValidationInfo) -> Image | None:
        if crop is not None:
            check_pixels(crop.data, image_limit(info, "max_crop_pixels"))
        return crop

    def views(self) -> list[str]:
        """The hash's four 16-bit bands: crops a few bits apart share most of them (locality
        sensitive hashing by bands), crops of other objects almost none."""
        return [f"{band}.{self.phash[4 * band:4 * band + 4]}" for band in range(4)] \
            if self.phash else []

    @staticmethod
    def similarities(a: list[ImageROI], b: list[ImageROI]) -> np.ndarray:
        """The thesis' g (eq. 6.1) of the Hamming distance of the perceptual hashes, sigma
        calibrated on the kitchen week's crops: the same object's hashes lie a median 4 bits
        apart (95 % within 12), different objects' a median 28 (95 % beyond 22)."""
        return compare.hash_nearness([x.phash for x in a], [y.phash for y in b],
                                     PHASH_SIGMA_BITS)

    def descriptors(self) -> dict[str, np.ndarray]:
        """The crop's colours and gradients (appearance.py), and the hash's bits."""
        found = {} if self.crop is None else crop_descriptors(
            self.crop.data, None if self.mask is None else self.mask.data)
        if self.phash is not None:
            found["phash"] = hash_bits(self.phash)
        return found


@stored_type("pm.hypothesis.PointCluster")
class PointCluster(Hypothesis):
    """A cluster of 3D points: its own small cloud, or indices into a scene cloud."""

    points: PointCloud | None = None
    indices: NDArray | None = None
    cloud: str = "cloud"  # which scene cloud `indices` refer to

    @model_validator(mode="after")
    def _points_or_indices(self) -> PointCluster:
        if self.points is None and self.indices is None:
            raise ValueError("a point cluster needs points or indices")
        return self


@stored_type("pm.hypothesis.SpatialVolume")
class SpatialVolume(Hypothesis):
    """A volume in a frame: an axis-aligned box (min and max corner) or a sphere. Used when
    something asserts an object without seeing it, e.g. after the robot put it down."""

    frame: str = "map"
    box_min: Vec3 | None = None
    box_max: Vec3 | None = None
    center: Vec3 | None = None
    radius: Finite | None = Field(default=None, ge=0)

    @model_validator(mode="after")
    def _box_or_sphere(self) -> SpatialVolume:
        box = self.box_min is not None and self.box_max is not None
        sphere = self.center is not None and self.radius is not None
        if box == sphere:
            raise ValueError("give either box_min and box_max, or center and radius")
        if box and any(lo > hi for lo, hi in zip(self.box_min, self.box_max, strict=True)):
            raise ValueError("box_min must not exceed box_max")
        return self

    def contains(self, points: np.ndarray) -> np.ndarray:
        """For each point (rows of x, y, z; NaN where unknown), whether it lies inside."""
        if self.center is not None:
            return np.linalg.norm(points - np.asarray(self.center), axis=1) <= self.radius
        return np.all((points >= self.box_min) & (points <= self.box_max), axis=1)
