"""What queries answer: pydantic models, so the Python API, the HTTP API (its OpenAPI schema)
and the CLI give the same shapes. Times are int64 nanoseconds since the epoch, UTC."""

from __future__ import annotations

import math
from typing import Annotated, Literal, Self

from pydantic import BaseModel, PlainSerializer

from percept_memory.memory.types import Id


class Moment:
    """Marks an int field as a moment: int64 nanoseconds since the epoch, UTC (so that the
    command line can show it in ISO 8601)."""


Nanoseconds = Annotated[int, Moment]
NOW = 2**63 - 1  # a question about now asks about the newest belief: at or before any time


def _null_for_now(ns: int) -> int | None:
    return None if ns == NOW else ns


AskedTime = Annotated[int, Moment, PlainSerializer(_null_for_now, return_type=int | None,
                                                   when_used="json")]
"""The moment a question was asked about: null in JSON when it was now (not int64's top)."""
Position = tuple[float, float, float]
State = Literal["present", "hidden", "disappeared"]


class ClusterHit(BaseModel):
    """One observation found: where and when, what it was called, which object it is."""

    id: Id
    scene_id: Id | None = None
    object_id: Id | None = None
    time: Nanoseconds
    robot: str
    region: str | None = None
    position: Position | None = None
    labels: list[str] = []
    text: list[str] = []
    types: list[str] = []
    score: float | None = None  # with sort=relevance
    distance: float | None = None  # with near

    @classmethod
    def of(cls, doc: dict, **more) -> Self:
        """The hit of a cluster's document (HIT_FIELDS), with a subclass's `more` fields."""
        search = doc["search"]
        return cls(id=doc["_id"], scene_id=doc.get("scene_id"), object_id=doc.get("object_id"),
                   time=search["time"], robot=search["robot"], region=search.get("region"),
                   position=search.get("position"), labels=search.get("labels", []),
                   text=search.get("text", []), types=search.get("types", []),
                   score=doc.get("score"), distance=doc.get("distance"), **more)


class ClusterPage(BaseModel):
    items: list[ClusterHit]
    next: str | None = None  # the cursor of the next page; None on the last
    total: int | None = None  # with count=true


def position_sigma(believed: dict) -> list[float] | None:
    """The standard deviation of a stored object's estimated place along x, y, z, when its
    observations declared their noise (consolidation.estimated_place keeps its variance)."""
    variance = believed.get("position_variance")
    return None if variance is None else [math.sqrt(v) for v in variance]


class Belief(BaseModel):
    """What the memory believes about one object now (where_is, last_seen)."""

    object_id: Id
    map: str | None = None  # the map it is believed in
    name: str | None = None
    names: list[str] = []
    state: State
    region: str | None = None
    position: Position | None = None
    # its standard deviation along x, y, z, when the observations declared their noise
    position_sigma: Position | None = None
    first_seen: Nanoseconds | None = None
    last_seen: Nanoseconds | None = None
    last_cluster: Id | None = None
    last_scene: Id | None = None
    robot: str | None = None
    observations: int = 0
    confidence: float | None = None  # probability of the explanation of its last event
    evidence: list[Id] = []  # its most recent observations (cluster ids), newest first
    match: float = 1.0  # how well it matches the question's text (1: every word exactly)


class Sighting(BaseModel):
    """When and where an object was last observed (last_seen)."""

    object_id: Id
    name: str | None = None
    time: Nanoseconds
    region: str | None = None
    position: Position | None = None
    cluster_id: Id | None = None
    scene_id: Id | None = None
    robot: str | None = None
    state: State  # what is believed of it now
    match: float = 1.0


class Stay(BaseModel):
    """One place an object was at, and when (where_was)."""

    region: str | None = None
    position: Position | None = None
    since: Nanoseconds  # when it was first seen there
    last_seen: Nanoseconds  # when it was last seen there
    hidden_since: Nanoseconds | None = None  # out of view from then on, still believed there
    until: Nanoseconds | None = None  # when it was found gone or elsewhere; None: still there
    ended_by: Literal["move", "disappear"] | None = None
    observations: int = 0


class History(BaseModel):
    object: Belief
    places: list[Stay]  # the latest MAX_PLACES, oldest first
    earlier_places: int = 0  # those before them, left out: a time window reaches them


class ObjectAt(BaseModel):
    """An object believed at a place at a moment (what_is_at, changes)."""

    object_id: Id
    map: str | None = None
    name: str | None = None
    state: State
    region: str | None = None
    position: Position | None = None
    since: Nanoseconds  # when it came there (its appear or move); disappeared: when found gone
    explanation: str  # the latest event's explanation: appear, stay, move, newview, hidden, ...
    # the observation that made it so; none when the event was no observation (its place
    # seen without it: hidden, gone): where_was and last_seen give its last one
    cluster_id: Id | None = None


class Contents(BaseModel):
    t: AskedTime
    objects: list[ObjectAt]


class Moved(BaseModel):
    object_id: Id
    name: str | None = None
    before: ObjectAt | None  # where it was at t1 (None: not at the place)
    after: ObjectAt | None  # where it is at t2 (None: gone from the memory's view)


class Changes(BaseModel):
    t1: Nanoseconds
    t2: AskedTime
    appeared: list[ObjectAt]  # at the place at t2, not at t1
    disappeared: list[Moved]  # at the place at t1, not at t2 (`after`: where it went)
    moved: list[Moved]  # at the place at both times, moved in between


class Count(BaseModel):
    type: str
    annotator: str | None = None
    count: int


class AnnotationStats(BaseModel):
    clusters: int
    by_type: list[Count]
    by_annotator: list[Count]


class Occurrence(BaseModel):
    object_id: Id | None = None
    name: str | None = None
    region: str | None = None
    hour: int | None = None  # of the day, UTC, with by_hour
    count: int


class CooccurrenceStats(BaseModel):
    rows: list[Occurrence]  # per object, region (and hour)
    regions: list[Occurrence]  # summed over the objects: where they usually are


class Timing(BaseModel):
    annotator: str
    runs: int
    mean_ms: float | None = None
    max_ms: float | None = None
    total_ms: float = 0.0
    warnings: int = 0
    errors: int = 0


class TimingStats(BaseModel):
    scenes: int
    annotators: list[Timing]


class Frame(BaseModel):
    """One scene of a robot's sequence, and where the sequence goes from it."""

    scene_id: Id
    robot: str
    map: str
    time: Nanoseconds
    clusters: int
    failed: list[str] = []  # the annotators with an error line in the scene's log
    first: Nanoseconds  # the sequence's first scene (the robot's, in the map if one is given)
    last: Nanoseconds  # and its last
    previous: Nanoseconds | None = None  # the sequence's scene before this one
    next: Nanoseconds | None = None  # and after it


class AnnotatorTotals(BaseModel):
    """One annotator's work over a window of scenes; times in milliseconds."""

    annotator: str
    annotations: int = 0
    runs: int = 0  # log lines with a duration
    mean_ms: float | None = None
    p95_ms: float | None = None
    max_ms: float | None = None
    warnings: int = 0  # log lines
    errors: int = 0


class AnnotatorHour(BaseModel):
    """One annotator in one hour (UTC) of the window: its times' median and 95th percentile,
    and in how many of the hour's scenes it warned or failed."""

    annotator: str
    hour: Nanoseconds  # the hour's start
    scenes: int  # of the window in that hour, the annotator's or not
    runs: int
    p50_ms: float | None = None
    p95_ms: float | None = None
    warned: int = 0  # scenes with a warning line of the annotator
    failed: int = 0  # scenes with an error line of the annotator


class ProblemLine(BaseModel):
    scene_id: Id
    time: Nanoseconds  # the scene's
    annotator: str
    level: str
    message: str


class ConfusionCount(BaseModel):
    said: str | None  # the annotator's class (None: it said nothing)
    expected: str | None  # the reference's
    clusters: int


class ClassScore(BaseModel):
    """Against the reference: of the clusters the annotator called this class (and the
    reference classified), the share the reference calls so too (precision); of those the
    reference calls so, the share the annotator called so (recall)."""

    class_name: str
    precision: float | None = None
    recall: float | None = None
    support: int = 0  # clusters the reference calls this class


class Comparison(BaseModel):
    """The classes an annotator gave against a reference's (another annotator, or the ground
    truth), on the clusters of the window either classified."""

    annotator: str
    reference: str
    clusters: int
    disagreements: int  # clusters on which they named different classes (or one none)
    cells: list[ConfusionCount]
    scores: list[ClassScore]


class AnnotatorReport(BaseModel):
    scenes: int
    first: Nanoseconds | None = None  # the window's oldest scene
    last: Nanoseconds | None = None  # and newest
    annotators: list[AnnotatorTotals]
    hours: list[AnnotatorHour]
    problems: list[ProblemLine]  # the latest warning and error lines, newest first
    comparisons: list[Comparison]


class Verdicts(BaseModel):
    """A cluster and the classes each annotator (and the ground truth) gave it."""

    id: Id
    scene_id: Id
    time: Nanoseconds
    verdicts: dict[str, list[str]]


class CellClusters(BaseModel):
    total: int
    clusters: list[Verdicts]  # newest first, at most the query's limit
