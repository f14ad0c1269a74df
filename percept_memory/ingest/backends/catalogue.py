"""A local product catalogue as a lookup backend (thesis 5.3: ODUFinder matched SIFT features
against the product images of an online store).

A catalogue is a folder: `products.json` ({"products": [{id, image, name, brand, category,
properties, source}]}) and one image per product. A crop matches a product when their pHashes
are within 10 bits (the same picture), or else by local features: SIFT keypoints of both,
scaled so the longer side is 256 px, Lowe's ratio test, then a RANSAC homography; the product
with the most inliers wins if it has at least 8 and twice as many as the runner-up, and the
homography is plausible (not folded or squashed). On the RoboSherlock frames the right
product gets 9-230 inliers (shifted, scaled, rotated, re-encoded), others 0-43 (crops of
cluttered scenes hold parts of their neighbours), regions that are no product 0. A match
answers a product result (name, brand, category and key-values) and, for a branded product,
a logo result; no match answers nothing, which is cached as well.

The shipped catalogue (`products/`, 12 products, ~100 kB) is cut from the real RoboSherlock
sample frames; `source` records the frame and box of each image, and
`python -m percept_memory.ingest.backends.catalogue ROBOSHERLOCK_DIR` cuts them again. The
samples carry no labels: names were given by looking at the frames, brands where the package
shows one.
"""

from __future__ import annotations

import asyncio
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from percept_memory.ingest.errors import BackendSetupError
from percept_memory.ingest.phash import crop_phash, hamming

from . import Finding

SHIPPED = Path(__file__).with_name("products")
PHASH_RADIUS = 10  # the lookup cache's default radius: the same picture
SIDE = 256  # features are found on images scaled to this longer side
RATIO = 0.75  # Lowe's ratio test
MIN_MATCHES = 6  # good matches needed to fit a homography
MIN_INLIERS = 8
MARGIN = 2.0  # the best product needs this many times the runner-up's inliers
RANSAC_PX = 5.0
MAX_SCALE = 8.0  # area scale of a plausible crop -> product homography, either way


@dataclass
class CatalogueProduct:
    id: str
    name: str
    category: str
    brand: str | None = None
    properties: dict[str, str | bool | int | float] = field(default_factory=dict)
    phash: int = 0
    keypoints: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.float32))
    descriptors: np.ndarray | None = None
    size: tuple[int, int] = (0, 0)  # width, height on the feature scale

    def findings(self, box: tuple[float, float, float, float] | None) -> list[Finding]:
        properties = {"category": self.category, **self.properties}
        found = [Finding(category="product", title=self.name, brand=self.brand, box=box,
                         properties=properties)]
        if self.brand:
            found.append(Finding(category="logo", title=self.brand, box=box))
        return found


def features(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, float]:
    """SIFT keypoint positions and descriptors of an image scaled to SIDE, and that scale."""
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    scale = SIDE / max(grey.shape)
    grey = cv2.resize(grey, None, fx=scale, fy=scale,
                      interpolation=cv2.INTER_LINEAR if scale > 1 else cv2.INTER_AREA)
    keypoints, descriptors = cv2.SIFT_create().detectAndCompute(grey, None)
    points = np.float32([k.pt for k in keypoints]).reshape(-1, 2)
    return points, descriptors, scale


class ProductCatalogue:
    """The catalogue backend: products matched by pHash, then by SIFT features."""

    name = "catalogue"

    def __init__(self, products: list[CatalogueProduct]):
        self.products = products

    @classmethod
    def load(cls, folder: Path | None = None) -> ProductCatalogue:
        folder = folder or SHIPPED
        listing = folder / "products.json"
        try:
            entries = json.loads(listing.read_text())["products"]
        except (OSError, ValueError, KeyError) as error:
            raise BackendSetupError(
                f"no product catalogue at {listing}: {error}; set PMEM_CATALOGUE_DIR to a "
                "folder with products.json and the product images") from None
        products = []
        for entry in entries:
            image = cv2.imread(str(folder / entry["image"]), cv2.IMREAD_COLOR)
            if image is None:
                raise BackendSetupError(f"catalogue image {folder / entry['image']} is unreadable")
            points, descriptors, scale = features(image)
            products.append(CatalogueProduct(
                id=entry["id"], name=entry["name"], category=entry["category"],
                brand=entry.get("brand"), properties=entry.get("properties", {}),
                phash=crop_phash(image), keypoints=points, descriptors=descriptors,
                size=(round(image.shape[1] * scale), round(image.shape[0] * scale))))
        return cls(products)

    async def lookup(self, crop: np.ndarray) -> list[Finding]:
        return await asyncio.to_thread(self.match, crop)

    async def aclose(self) -> None:
        pass

    def match(self, crop: np.ndarray) -> list[Finding]:
        """What the catalogue says about a crop: its product, or nothing."""
        query = crop_phash(crop)
        same = min(self.products, key=lambda p: hamming(p.phash, query), default=None)
        if same is not None and hamming(same.phash, query) <= PHASH_RADIUS:
            return same.findings((0.0, 0.0, float(crop.shape[1]), float(crop.shape[0])))
        points, descriptors, scale = features(crop)
        if descriptors is None or len(descriptors) < 2:
            return []
        scored = sorted(((self._inliers(points, descriptors, p), p) for p in self.products),
                        key=lambda s: s[0][0], reverse=True)
        (best, homography), product = scored[0]
        runner_up = scored[1][0][0] if len(scored) > 1 else 0
        if best < MIN_INLIERS or best < MARGIN * runner_up:
            return []
        return product.findings(_box(homography, product.size, scale, crop.shape))

    @staticmethod
    def _inliers(points, descriptors, product: CatalogueProduct) -> tuple[int, np.ndarray | None]:
        """RANSAC inliers of the crop -> product homography, and the homography."""
        if product.descriptors is None or len(product.descriptors) < 2:
            return 0, None
        pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(descriptors, product.descriptors, k=2)
        good = [m for m, *rest in pairs if rest and m.distance < RATIO * rest[0].distance]
        if len(good) < MIN_MATCHES:
            return 0, None
        source = points[[m.queryIdx for m in good]]
        target = product.keypoints[[m.trainIdx for m in good]]
        homography, mask = cv2.findHomography(source, target, cv2.RANSAC, RANSAC_PX)
        if homography is None or not _plausible(homography, product.size):
            return 0, None
        return int(mask.sum()), homography


def _plausible(homography: np.ndarray, size: tuple[int, int]) -> bool:
    """Could this homography be a view of a flat picture? Repetitive structure (drawer fronts,
    tiles) fits degenerate ones with many inliers: folded (corners no longer convex) or squashed
    (area scale far from the 1 that scaling both images to SIDE makes of the same object)."""
    area_scale = abs(np.linalg.det(homography[:2, :2]))
    if not 1 / MAX_SCALE <= area_scale <= MAX_SCALE:
        return False
    width, height = size
    corners = np.float32([[0, 0], [width, 0], [width, height], [0, height]]).reshape(-1, 1, 2)
    projected = cv2.perspectiveTransform(corners, homography)
    return bool(cv2.isContourConvex(projected.astype(np.float32)))


def _box(homography: np.ndarray, size: tuple[int, int], scale: float,
         shape: tuple[int, ...]) -> tuple[float, float, float, float] | None:
    """Where the product's picture lies in the crop (crop pixels), from the homography."""
    try:
        inverse = np.linalg.inv(homography)
    except np.linalg.LinAlgError:
        return None
    width, height = size
    corners = np.float32([[0, 0], [width, 0], [width, height], [0, height]]).reshape(-1, 1, 2)
    projected = cv2.perspectiveTransform(corners, inverse).reshape(-1, 2) / scale
    low = np.clip(projected.min(axis=0), 0, [shape[1], shape[0]])
    high = np.clip(projected.max(axis=0), 0, [shape[1], shape[0]])
    if np.any(high <= low):
        return None
    x, y = (round(float(v), 1) for v in low)
    return x, y, round(float(high[0] - low[0]), 1), round(float(high[1] - low[1]), 1)


def cut_images(robosherlock: Path, folder: Path = SHIPPED) -> None:
    """(Re)make the catalogue's images from the frames and boxes its `source` fields name."""
    for entry in json.loads((folder / "products.json").read_text())["products"]:
        frame = cv2.imread(str(robosherlock / entry["source"]["frame"]), cv2.IMREAD_COLOR)
        x, y, w, h = entry["source"]["box"]
        cv2.imwrite(str(folder / entry["image"]), frame[y : y + h, x : x + w],
                    [cv2.IMWRITE_JPEG_QUALITY, 90])


if __name__ == "__main__":
    cut_images(Path(sys.argv[1]))
