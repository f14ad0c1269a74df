"""Synthetic but realistic percepts, for benchmarks, tests and the demo.

A cluster looks like one of RoboSherlock's: an image ROI with a 64 px crop, mask and pHash, and
20 annotations from as many annotators (location, classification with per-class confidences,
shape, colours, a 16x16 colour histogram, a 308-float VFH descriptor, OCR text, logo, product,
barcode, web lookups, tracking, geometry, ...). Crops are cut from a real image when one is
given, so PNG sizes and timings are those of real pixels.
"""

from __future__ import annotations

import numpy as np

from percept_memory.memory.types import (
    Barcode,
    CameraInfo,
    Classification,
    Cluster,
    ColorHistogram,
    Detection,
    FeatureVector,
    Geometry,
    Image,
    ImageROI,
    Location,
    LogLine,
    Logo,
    Pose,
    Product,
    Relation,
    Scene,
    SemanticColor,
    Shape,
    Text,
    Tracking,
    Transform,
    WebLookup,
)

CLASSES = ["cereal", "juice", "bowl", "plate", "spoon", "glass", "knife", "cup"]
SHAPES = ["box", "cylinder", "flat", "round"]
COLOURS = ["red", "yellow", "green", "blue", "white", "black", "grey"]
BRANDS = ["Kelloggs", "Pringles", "Lipton", "Milka", "Hohes C", "Ja!"]
REGIONS = ["counter_top_sink", "counter_top_island", "table_center", "shelf_top"]
CROP = 64
KINECT = CameraInfo(width=640, height=480, k=(525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1),
                    d=[0.0] * 5, frame="head_mount_kinect_rgb_optical_frame")


def _crop(rng: np.random.Generator, image: np.ndarray | None) -> tuple[tuple, np.ndarray]:
    if image is None:
        return (0, 0, CROP, CROP), rng.integers(0, 256, (CROP, CROP, 3), dtype=np.uint8)
    y = int(rng.integers(0, image.shape[0] - CROP))
    x = int(rng.integers(0, image.shape[1] - CROP))
    return (x, y, CROP, CROP), image[y : y + CROP, x : x + CROP].copy()


def cluster(rng: np.random.Generator, image: np.ndarray | None = None) -> Cluster:
    """A cluster with an ImageROI (64 px crop) and 20 annotations."""
    box, crop = _crop(rng, image)
    name = str(rng.choice(CLASSES))
    brand = str(rng.choice(BRANDS))
    confidences = rng.dirichlet(np.ones(len(CLASSES)))
    colours = rng.dirichlet(np.ones(3))
    position = tuple(float(v) for v in rng.normal((1.0, 0.5, 0.9), (0.5, 0.5, 0.05)))
    return Cluster(
        hypotheses=[
            ImageROI(
                box=box,
                crop=Image(data=crop, encoding="bgr8"),
                mask=Image(data=np.full((CROP, CROP), 255, np.uint8), encoding="mono8"),
                phash=f"{int(rng.integers(0, 2**63)):016x}",
            )
        ],
        annotations=[
            Location(source="RegionFilter", region=str(rng.choice(REGIONS)), position=position,
                     relation="on"),
            Classification(source="SVMClassifier", class_name=name,
                           confidence=float(confidences.max()), classifier="SVM",
                           feature="VFH", confidences=dict(zip(CLASSES, confidences.tolist(),
                                                               strict=True))),
            Classification(source="KNNClassifier", class_name=name, classifier="kNN",
                           feature="CNN", confidence=0.7),
            Detection(source="DeCafClassifier", name=name, confidence=0.73, box=box),
            Shape(source="PrimitiveShapeAnnotator", shape=str(rng.choice(SHAPES)),
                  confidence=0.63),
            SemanticColor(source="ClusterColorHistogramCalculator",
                          ratios=dict(zip(rng.choice(COLOURS, 3, replace=False).tolist(),
                                          colours.tolist(), strict=True))),
            ColorHistogram(source="ClusterColorHistogramCalculator",
                           histogram=rng.random((16, 16), dtype=np.float32)),
            FeatureVector(source="PCLDescriptorExtractor", name="VFH",
                          vector=rng.random(308, dtype=np.float32)),
            Text(source="OCRAnnotator", text=f"{brand} {name} original", confidence=0.81),
            Text(source="GogglesAnnotator", text=f"{name.upper()} 500g"),
            Logo(source="GogglesAnnotator", brand=brand, confidence=0.9),
            Product(source="GogglesAnnotator", name=f"{brand} {name}", brand=brand,
                    properties={"category": "food", "weight_g": 500, "perishable": False}),
            Barcode(source="ZBarAnnotator", code=f"{int(rng.integers(10**12, 10**13))}",
                    symbology="EAN13"),
            WebLookup(source="GogglesAnnotator", service="goggles", category="logo",
                      title=brand, box=box, links=[f"https://example.org/{brand}"]),
            WebLookup(source="GogglesAnnotator", service="goggles", category="product",
                      title=f"{brand} {name}", links=[]),
            WebLookup(source="GogglesAnnotator", service="goggles", category="similar_image",
                      title=f"{name} on a table"),
            Tracking(source="ObjectIdentityResolution", tracking_id=int(rng.integers(0, 1000))),
            Geometry(source="Cluster3DGeometryAnnotator", size=(0.08, 0.06, 0.2),
                     volume=0.00096, pose=Pose(translation=position), semantic_size="small"),
            Relation(source="SpatialRelationAnnotator", predicate="on", a="cluster",
                     b="counter", probability=0.9),
            LogLine(source="RegionFilter", message="cluster inside region", duration_ms=0.4),
        ],
    )


def scene(
    rng: np.random.Generator,
    timestamp: int,
    clusters: int = 6,
    image: np.ndarray | None = None,
    robot: str = "pr2",
) -> Scene:
    """A scene from a Kinect on the robot's head with `clusters` realistic clusters."""
    return Scene(
        timestamp=timestamp,
        robot=robot,
        camera_pose=Transform(translation=(0.0, 0.5, 1.5), rotation=(0.0, 0.5, 0.0, 0.866),
                              child_frame=KINECT.frame, stamp=timestamp),
        camera=KINECT,
        clusters=[cluster(rng, image) for _ in range(clusters)],
        log=[LogLine(source="CollectionReader", message="frame received", time=timestamp),
             LogLine(source="PlaneAnnotator", message="plane found", duration_ms=12.5)],
    )
