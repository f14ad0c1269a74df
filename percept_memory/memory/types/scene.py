"""Clusters and scenes (thesis 3.2.4): an object hypothesis with everything said about it, and
a timestamped snapshot of what the robot saw."""

from __future__ import annotations

from typing import TypeVar

import numpy as np
from pydantic import Field, model_validator

from .annotations import Annotation, Location, LogLine, Relation
from .base import Id, Identifiable, Name, Timestamp, polymorphic, stored_type
from .hypotheses import Hypothesis, SpatialVolume
from .raw import CameraInfo, Image, PointCloud, Transform, Vec3

A = TypeVar("A", bound=Annotation)
MAX_CLUSTERS = 1000  # per scene: a scene is stored in one transaction


@stored_type("pm.scene.Cluster")
class Cluster(Identifiable):
    """One object hypothesis in one scene and the annotations of all annotators on it.
    Annotations of types this version does not know are kept as `Unknown`."""

    scene_id: Id | None = None
    object_id: Id | None = None  # the physical object this observation is believed to be
    hypotheses: list[polymorphic(Hypothesis)] = []
    annotations: list[polymorphic(Annotation)] = []
    # How many of `annotations` came with the scene; those after were appended later
    # (enrichment's lookups, people's corrections). Identity and the catalogue decide on those
    # that came with it, so a stored cluster handed on (a scene log) is decided alike again.
    arrived: int | None = Field(default=None, ge=0, description=(
        "how many of the annotations came with the scene, the rest appended later "
        "(enrichment, corrections); unset: all"))

    @model_validator(mode="after")
    def _arrived_among_annotations(self) -> Cluster:
        if self.arrived is not None and self.arrived > len(self.annotations):
            raise ValueError(f"arrived: {self.arrived} annotations arrived, but the cluster "
                             f"has {len(self.annotations)}")
        return self

    def annotations_arrived(self) -> list:
        """The annotations that came with the scene (all, unless `arrived` says fewer)."""
        return self.annotations if self.arrived is None else self.annotations[:self.arrived]

    def annotations_of(self, kind: type[A]) -> list[A]:
        return [a for a in self.annotations if isinstance(a, kind)]

    def hypothesis_of(self, kind: type[Hypothesis]) -> Hypothesis | None:
        return next((h for h in self.hypotheses if isinstance(h, kind)), None)

    def descriptors(self) -> dict[str, np.ndarray]:
        """Name -> unit vector over its hypotheses and annotations (the first of each name):
        what similarity search compares it by."""
        found: dict[str, np.ndarray] = {}
        for part in (*self.hypotheses, *self.annotations):
            if isinstance(part, Hypothesis | Annotation):
                for name, vector in part.descriptors().items():
                    found.setdefault(name, vector)
        return found

    def location(self) -> Location | None:
        """The first location annotation that gives a position or region."""
        return next(
            (a for a in self.annotations_of(Location) if a.position or a.region), None
        )

    @property
    def position(self) -> Vec3 | None:
        location = self.location()
        return location.position if location else None

    @property
    def position_variance(self) -> Vec3 | None:
        """The declared variance of the position along each axis (Location.position_sigma)."""
        location = self.location()
        sigma = location.position_sigma if location and location.position else None
        return None if sigma is None else tuple(s * s for s in sigma)

    @property
    def region(self) -> str | None:
        location = self.location()
        return location.region if location else None


@stored_type("pm.scene.Scene")
class Scene(Identifiable):
    """What one robot saw at one instant: camera pose and intrinsics, transforms, images,
    clusters, the relations table, scene-level annotations and the annotators' log."""

    timestamp: Timestamp
    robot: Name = ""
    frame: Name = "map"
    # The unit of space: regions, objects and the belief are per map, and observations in two
    # maps are never one object. Default: the robot and its frame ("pr2/map"), given when the
    # scene is validated.
    map: Name = Field("", description=(
        "the map (site) the scene belongs to; default: robot/frame"))
    camera_pose: Transform | None = None  # the camera in `frame`
    camera: CameraInfo | None = None
    # What the sensor saw, when the scene says so (in `frame`); else the camera's frustum
    view_region: SpatialVolume | None = None
    transforms: list[Transform] = []
    images: dict[Name, Image] = {}
    clouds: dict[str, PointCloud] = {}
    clusters: list[Cluster] = Field([], max_length=MAX_CLUSTERS)
    relations: list[Relation] = []
    annotations: list[polymorphic(Annotation)] = []
    log: list[LogLine] = []

    @model_validator(mode="after")
    def _ids_once(self) -> Scene:
        """An id names one stored document: two clusters (or two annotations of one
        cluster) given the same id cannot both be stored."""
        _once([c.id for c in self.clusters], "clusters")
        for index, cluster in enumerate(self.clusters):
            _once([a.id if isinstance(a, Identifiable) else a.fields.get("_id")
                   for a in cluster.annotations], f"clusters.{index}.annotations")
        return self

    @model_validator(mode="after")
    def _default_map(self) -> Scene:
        if not self.map:
            self.map = default_map(self.robot, self.frame)
        return self


def _once(ids: list, where: str) -> None:
    seen = set()
    for given in ids:
        if given is not None and given in seen:
            raise ValueError(f"{where}: the id {given} is given twice")
        seen.add(given)


def default_map(robot: str, frame: str) -> str:
    """The map of a scene that names none: its robot's frame."""
    return f"{robot}/{frame}" if robot else frame
