"""What every format shares: the items to write, class ids, the provenance sidecar, the
pictures (scene images or crops) with the clusters' boxes, and the count of what was skipped."""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

from percept_memory.memory.types import Cluster, Scene, datetime_from_timestamp

from . import pixels
from .archive import Archive, Spool, file_name
from .labels import Label
from .model import ExportQuery

PROVENANCE = "provenance.jsonl"


@dataclass(frozen=True)
class Item:
    """A selected cluster with its label, in its scene."""

    scene: Scene
    cluster: Cluster
    label: Label


@dataclass
class Summary:
    exported: int = 0
    corrected: int = 0  # of the exported, those labelled by a person's correction
    skipped: Counter = field(default_factory=Counter)  # reason -> clusters

    def skipped_text(self) -> str:
        """What was skipped and why, for people: "30 (no classification label), ..."."""
        return ", ".join(f"{count} ({reason})" for reason, count in sorted(self.skipped.items()))

    def why_empty(self) -> str:
        """Why an export holds no cluster: what the CLI's error and the API's 422 say."""
        if not self.skipped:
            return "nothing exported: the query selects no clusters"
        return f"nothing exported: every selected cluster was skipped: {self.skipped_text()}"


@dataclass
class Picture:
    """An image to export and the objects in it."""

    stem: str  # the file name without extension: a scene id and image name, or a cluster id
    png: bytes
    instances: list[tuple[Item, pixels.Instance]]


class Writer(ABC):
    """Base of the formats. `add` takes a scene's items, `finish` writes what is left."""

    def __init__(self, archive: Archive, query: ExportQuery, summary: Summary):
        self.archive, self.query, self.summary = archive, query, summary
        self.provenance = Spool()
        self.classes: dict[str, int] = {}  # label -> class id, in order of first appearance

    @abstractmethod
    def add(self, items: list[Item]) -> None:
        """Write one scene's items in the format (each format has its own)."""

    def finish(self) -> None:
        """The format's own entries at the end; then the provenance sidecar."""
        self.archive.add(PROVENANCE, self.provenance.chunks(), self.provenance.size)

    def class_id(self, label: Label) -> int:
        return self.classes.setdefault(label.name, len(self.classes))

    def exported(self, item: Item, ref: dict) -> None:
        """Count the item and write its provenance, `ref` saying where it is in the export."""
        self.summary.exported += 1
        self.summary.corrected += item.label.corrected
        self.provenance.line({**ref, **provenance(item)})

    def skip(self, reason: str, count: int = 1) -> None:
        self.summary.skipped[reason] += count

    def pictures(self, items: list[Item]) -> Iterator[Picture]:
        """Scene images with every item's box in them, or each item's crop (query.images);
        auto: the scene image where the scene has the one the item's box is in, else the crop
        (the kitchen week's scenes have crops and no camera image)."""
        if self.query.images == "auto":
            in_scene: list[Item] = []
            cropped: list[Item] = []
            for item in items:
                has_image = pixels.scene_roi(item.cluster, item.scene) is not None
                (in_scene if has_image else cropped).append(item)
            yield from self._scene_pictures(in_scene)
            yield from self._crop_pictures(cropped)
        elif self.query.images == "scenes":
            yield from self._scene_pictures(items)
        else:
            yield from self._crop_pictures(items)

    def _crop_pictures(self, items: list[Item]) -> Iterator[Picture]:
        for item in items:
            found = pixels.crop_of(item.cluster, item.scene)
            if found is None:
                self.skip("no crop and no scene image")
            elif (data := pixels.png(found[1])) is None:
                self.skip("the crop is not an 8 or 16-bit image")
            else:
                yield Picture(str(item.cluster.id), data,
                              [(item, pixels.in_crop(found[0], found[1]))])

    def _scene_pictures(self, items: list[Item]) -> Iterator[Picture]:
        by_image: dict[str, list[tuple[Item, pixels.Instance]]] = {}
        for item in items:
            roi = pixels.scene_roi(item.cluster, item.scene)
            if roi is None:
                self.skip("the scene has no image the cluster's box is in")
            elif (instance := pixels.in_scene(roi, item.scene.images[roi.image])) is None:
                self.skip("the cluster's box lies outside its image")
            else:
                by_image.setdefault(roi.image, []).append((item, instance))
        for name, instances in by_image.items():
            scene = instances[0][0].scene
            data = pixels.png(scene.images[name])
            if data is None:
                self.skip("the scene image is not an 8 or 16-bit image", len(instances))
            else:
                yield Picture(picture_stem(scene.id, name), data, instances)


def picture_stem(scene_id, image: str) -> str:
    """A scene image's file name: the scene's id and the image's name as a file name, with a
    digest of the name when it had to change or has capitals (two names must not give one
    file, rgb and RGB neither, on a file system that does not tell case apart)."""
    safe = file_name(image)
    if safe != image.lower():
        safe += "_" + hashlib.sha1(image.encode()).hexdigest()[:8]
    return f"{scene_id}_{safe}"


def provenance(item: Item) -> dict:
    """Where a training example came from: scene, time, camera pose, place, label source
    (`corrected`: the label is a person's correction, the annotator `human:<author>`)."""
    scene, cluster, label = item.scene, item.cluster, item.label
    pose = scene.camera_pose
    return {
        "cluster_id": str(cluster.id),
        "scene_id": str(scene.id),
        "object_id": None if cluster.object_id is None else str(cluster.object_id),
        "robot": scene.robot,
        "frame": scene.frame,
        "time": scene.timestamp,
        "time_utc": datetime_from_timestamp(scene.timestamp).isoformat(),
        "camera_pose": None if pose is None else pose.model_dump(
            mode="json", include={"translation", "rotation", "frame", "child_frame", "stamp"}),
        "region": cluster.region,
        "position": cluster.position,
        "label": label.name,
        "annotator": label.annotator,
        "annotation_id": None if label.annotation_id is None else str(label.annotation_id),
        "corrected": label.corrected,
    }
