"""The typed query model: one set of pydantic models behind the Python API, the HTTP API
(query string and JSON body) and `pmem query`.

Every value is validated here into plain data (strings, numbers, ids, times); compile.py only
ever places such values where MongoDB reads values, so nothing a user sends can become an
operator. Limits (page size, list lengths, words, predicates) bound what one query may cost.
Compact text forms exist for the query string and the command line: a box is
"x0,y0,z0,x1,y1,z1", a sphere "x,y,z,r", a predicate "classification:confidence>0.8".
"""

from __future__ import annotations

import enum
import json
import math
import re
import time
import types
import typing
from datetime import datetime
from typing import Annotated, Any, Literal

from bson import ObjectId
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    StringConstraints,
    TypeAdapter,
    ValidationError,
    model_validator,
)

from percept_memory.converters import class_for, name_of, registered_types
from percept_memory.converters.registry import close_names, is_reserved
from percept_memory.memory.search_keys import field_key, field_path, normal_label, words
from percept_memory.memory.types import (
    Annotation,
    Id,
    datetime_from_timestamp,
    timestamp_from_datetime,
    timestamp_from_iso,
)

MAX_PAGE = 500
MAX_K = 1000
MAX_LIST = 32
MAX_PREDICATES = 16
MAX_WORDS = 16
MAX_TEXT = 500
MAX_ANSWERS = 50

Name = Annotated[str, StringConstraints(min_length=1, max_length=200)]


SPACED_OFFSET = re.compile(r"\d \d\d(:?\d\d)?$")  # 08:00 01:00: a + the URL turned to a space


def _nanoseconds(value: Any) -> Any:
    """A time given as nanoseconds since the epoch (int or digits) or ISO 8601 (naive is UTC)."""
    if isinstance(value, datetime):
        value = timestamp_from_datetime(value)
    elif isinstance(value, str):
        if value.strip().isdigit():
            value = int(value)
        else:
            try:
                value = timestamp_from_iso(value)
            except ValueError:
                plus = (" (a + in a URL's query string is read as a space: write it %2B)"
                        if SPACED_OFFSET.search(value) else "")
                raise ValueError(f"expected nanoseconds since the epoch or an ISO 8601 time "
                                 f"such as 2024-03-05T08:00, got {value!r}{plus}") from None
    if isinstance(value, bool):
        raise ValueError("expected a time, got a boolean")
    if isinstance(value, int) and not 0 <= value < 2**63:  # (said as times, not as 2**63)
        raise ValueError("expected a time from 1970-01-01 to 2262-04-11T23:47:16Z (int64 "
                         "nanoseconds since the epoch)")
    return value


Time = Annotated[int, BeforeValidator(_nanoseconds), Field(ge=0, lt=2**63)]
"""A moment: int64 nanoseconds since the epoch (UTC); ISO 8601 strings are accepted."""


def _numbers(count: int, what: str):
    def parse(value: Any) -> Any:
        if isinstance(value, str):
            parts = [p for p in re.split(r"[,\s]+", value.strip()) if p]
            if len(parts) != count:
                raise ValueError(f"expected {what}: {count} comma-separated numbers")
            try:
                return [float(p) for p in parts]
            except ValueError:
                raise ValueError(f"expected {what}: {count} numbers, got {value!r}") from None
        if isinstance(value, list | tuple) and len(value) != count:
            raise ValueError(f"expected {what}: {count} numbers, got {len(value)}")
        return value

    return BeforeValidator(parse)


Finite = Annotated[float, Field(allow_inf_nan=False)]
Point = Annotated[tuple[Finite, Finite, Finite], _numbers(3, "a point x,y,z")]


def listed(value: Any) -> Any:
    """One value where a list is expected is a list of one."""
    return [value] if isinstance(value, str | int | float | dict) else value


class Strict(BaseModel):
    """Unknown fields are an error, so a misspelt parameter never silently widens a query."""

    model_config = ConfigDict(extra="forbid", frozen=True)


# --- space ----------------------------------------------------------------------------------


class Box(Strict):
    """An axis-aligned box in the map frame, corners included."""

    low: Point
    high: Point

    @model_validator(mode="before")
    @classmethod
    def _from_text(cls, value: Any) -> Any:
        if isinstance(value, str | list | tuple):  # "x0,y0,z0,x1,y1,z1", or its numbers
            corners = _numbers(6, "a box x0,y0,z0,x1,y1,z1").func(value)
            return {"low": corners[:3], "high": corners[3:]}
        return value

    @model_validator(mode="after")
    def _ordered(self) -> Box:
        if any(a > b for a, b in zip(self.low, self.high, strict=True)):
            raise ValueError("the box's low corner must not be above its high corner")
        return self


class Sphere(Strict):
    """The points within `radius` metres of `center` (the surface included)."""

    center: Point
    radius: Annotated[float, Field(gt=0, allow_inf_nan=False)]

    @model_validator(mode="before")
    @classmethod
    def _from_text(cls, value: Any) -> Any:
        if isinstance(value, str | list | tuple):  # "x,y,z,radius", or its numbers
            numbers = _numbers(4, "a sphere x,y,z,radius").func(value)
            return {"center": numbers[:3], "radius": numbers[3]}
        return value


# --- annotation field predicates ------------------------------------------------------------

OPERATORS = {"=": "$eq", "==": "$eq", "!=": "$ne", ">": "$gt", ">=": "$gte", "<": "$lt",
             "<=": "$lte"}
_PREDICATE = re.compile(
    r"^\s*(?P<type>[\w.]+)\s*:\s*(?P<field>[^<>=!:]+?)\s*(?P<op>==|!=|>=|<=|=|>|<)\s*"
    r"(?P<value>.*?)\s*$", re.DOTALL)
_SEGMENT = re.compile(r"^[^$.\x00][^.\x00]*$")
Scalar = str | bool | int | float | None


def annotation_types() -> dict[str, str]:
    """Short names (casefolded class names) of the registered annotation types -> names."""
    return {cls.__name__.casefold(): name for name, cls in registered_types().items()
            if issubclass(cls, Annotation)}


def canonical_type(given: str) -> str:
    """The stored `_type` of a type given by name, alias or short name ("classification")."""
    cls = class_for(given)
    if cls is not None and issubclass(cls, Annotation):
        return name_of(cls)
    short = annotation_types()
    if given.casefold() in short:
        return short[given.casefold()]
    if "." in given and cls is None and not is_reserved(given):
        return given  # a type this version does not know, kept as it was stored
    hint = close_names(given)
    raise ValueError(f"no annotation type {given!r}"
                     + (f" (did you mean {', '.join(hint)}?)" if hint else "")
                     + f": use a full dotted type name or one of {sorted(short)}")


class Predicate(Strict):
    """A comparison on a field of one annotation type: `classification:class_name=cylinder`.
    Several predicates on one type must hold on the same annotation. Fields of registered
    types are checked and values converted to the field's type; any other dotted type name
    is taken as stored, its values as JSON scalars (or text)."""

    type: Annotated[str, StringConstraints(pattern=r"^[\w.]+$", max_length=200)]
    field: Annotated[str, StringConstraints(min_length=1, max_length=200)]
    op: Literal["=", "==", "!=", ">", ">=", "<", "<="] = "="
    value: Any = Field(json_schema_extra={"type": ["string", "number", "boolean", "null"]})
    # of a type this program does not know, the BSON values the text may stand for too
    _alternatives: list = PrivateAttr(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _from_text(cls, value: Any) -> Any:
        if not isinstance(value, str):
            return value
        match = _PREDICATE.match(value)
        if match is None:
            raise ValueError(f"expected type:field<op>value, such as "
                             f"classification:confidence>0.8, got {value!r}")
        return {**match.groupdict(), "value": _TextValue(match["value"])}

    @model_validator(mode="after")
    def _resolved(self) -> Predicate:
        parts = self.field.split(".")
        if not all(_SEGMENT.match(part) for part in parts):
            raise ValueError(f"field {self.field!r}: parts must not be empty or start with $")
        name = canonical_type(self.type)
        stored, value = _resolve_field(name, parts, self.value)
        object.__setattr__(self, "type", name)
        object.__setattr__(self, "field", stored)
        object.__setattr__(self, "value", value)
        if class_for(name) is None:
            self._alternatives = _bson_values(value)
        return self

    @property
    def values(self) -> list:
        """The value, and for a type this program does not know, the id or time it may
        stand for: stored from Extended JSON ($oid, $date), those fields hold BSON values."""
        return [self.value, *self._alternatives]

    @property
    def key(self) -> str:
        """The field as people name it (`type:path`), and its index (store.add_field_index)."""
        return field_key(self.type, self.field)

    @property
    def operator(self) -> str:
        return OPERATORS[self.op]

    @property
    def label(self) -> str | None:
        """The label this predicate asks for exactly, when its field is one the type's
        labels come from (Annotation.label_fields): classification:class_name=Cereal asks
        for "cereal", which every cluster it matches is found by (search.labels)."""
        fields = getattr(class_for(self.type), "label_fields", ())
        if self.operator != "$eq" or not isinstance(self.value, str) or self.field not in fields:
            return None
        return normal_label(self.value) or None


class _TextValue(str):
    """A predicate value written as text (query string, CLI): its type is still to decide."""


def annotation_field(text: str) -> tuple[str, str]:
    """The stored type and field path of a field as a predicate names it, `type:field`
    ("classification:confidence", "product:properties.perishable"): ValueError if there is
    no such scalar field."""
    type_part, colon, field = (part.strip() for part in text.partition(":"))
    if not colon or not type_part or not field:
        raise ValueError(f"expected type:field, such as classification:confidence, got {text!r}")
    parts = field.split(".")
    if not all(_SEGMENT.match(part) for part in parts):
        raise ValueError(f"field {field!r}: parts must not be empty or start with $")
    name = canonical_type(type_part)
    path, kind = _stored_field(name, parts)
    if kind is not None and not _scalar(kind):
        raise ValueError(f"{name}:{field} is not a scalar field (a number, text or truth)")
    return name, path


def _scalar(kind: Any) -> bool:
    """Whether a field's values are numbers, texts, truths or times (what an index orders)."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is typing.Annotated:
        return _scalar(args[0])
    if origin in (typing.Union, types.UnionType):
        return all(_scalar(arm) for arm in args if arm is not type(None))
    return origin is typing.Literal or (isinstance(kind, type) and issubclass(
        kind, int | float | str | bool | enum.Enum | datetime))


def _a_time(kind: Any) -> bool:
    """Whether a field holds datetimes (stored as BSON dates)."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is typing.Annotated or origin in (typing.Union, types.UnionType):
        return any(_a_time(arm) for arm in args if arm is not type(None))
    return isinstance(kind, type) and issubclass(kind, datetime)


def _resolve_field(type_name: str, parts: list[str], value: Any) -> tuple[str, Scalar]:
    """The stored path of a field and the value converted to its type."""
    path, kind = _stored_field(type_name, parts)
    if kind is None:
        return path, _json_scalar(value)
    return path, _converted(value, kind, f"{type_name}:{parts[0]}")


def _stored_field(type_name: str, parts: list[str]) -> tuple[str, Any]:
    """The stored path of a field and its type (None: a type this program does not know)."""
    cls = class_for(type_name)
    if parts[0] in ("_type", "_id"):
        raise ValueError(f"{parts[0]} is not a field to compare: choose the type before ':'")
    if cls is None:
        return field_path(parts[0], parts[1:]), None
    fields = {key: (name, info) for name, info in cls.model_fields.items()
              for key in (name, info.alias) if key and name != "id"}
    if parts[0] not in fields:
        raise ValueError(f"{type_name} has no field {parts[0]!r}: one of "
                         f"{sorted(n for n in cls.model_fields if n != 'id')}")
    name, info = fields[parts[0]]
    stored = info.alias or name
    kind = info.annotation
    if len(parts) > 1:
        kind = _mapping_value_type(kind)
        if kind is None:
            raise ValueError(f"{type_name}.{parts[0]} is not a mapping: it has no "
                             f"{'.'.join(parts[1:])!r}")
        if len(parts) > 2:
            raise ValueError(f"field {'.'.join(parts)!r} is too deep: at most field.key")
    return field_path(stored, parts[1:]), kind


def _mapping_value_type(kind: Any) -> Any:
    for arm in (kind, *typing.get_args(kind)):
        if typing.get_origin(arm) is dict:
            return typing.get_args(arm)[1]
    return None


def _bson_values(value: Any) -> list:
    """The id (24 hexadecimal digits) or the time (ISO 8601) a text may stand for."""
    if not isinstance(value, str):
        return []
    if ObjectId.is_valid(value):
        return [ObjectId(value)]
    try:
        return [datetime_from_timestamp(timestamp_from_iso(value))]
    except ValueError:
        return []


def _json_scalar(value: Any) -> Scalar:
    """Text from a query string read as JSON where it is a JSON scalar ("0.8", "true"); a
    value from JSON must be a scalar itself (never a document such as {"$gt": ...})."""
    if isinstance(value, _TextValue):
        try:
            parsed = json.loads(value)
        except ValueError:
            return str(value)
        return parsed if isinstance(parsed, Scalar) else str(value)
    if not isinstance(value, Scalar) or (isinstance(value, float) and not math.isfinite(value)):
        raise ValueError(f"a predicate's value must be a string, number, boolean or null, "
                         f"not {type(value).__name__}")
    return value


def _converted(value: Any, kind: Any, where: str) -> Scalar | datetime:
    if _a_time(kind):  # as every time here: ISO 8601 (naive is UTC) or nanoseconds
        try:
            return datetime_from_timestamp(TypeAdapter(Time).validate_python(str(value)))
        except ValidationError:
            raise ValueError(f"{str(value)!r} is not a valid value for {where}: a time is "
                             "ISO 8601 or nanoseconds since the epoch") from None
    first = _json_scalar(value)
    candidates = [first, str(value)] if isinstance(value, _TextValue) else [first]
    adapter = TypeAdapter(kind)
    for candidate in candidates:
        try:
            converted = adapter.validate_python(candidate)
        except ValidationError:
            continue
        if isinstance(converted, Scalar) and not (
                isinstance(converted, float) and math.isnan(converted)):
            return converted
        raise ValueError(f"{where} is not a scalar field: compare its parts (field.key)")
    raise ValueError(f"{str(value)!r} is not a valid value for {where}")


# --- what clusters to find -------------------------------------------------------------------

Sort = Literal["newest", "oldest", "relevance", "distance"]


class ClusterFilter(Strict):
    """Which clusters (object observations): every given condition must hold."""

    text: Annotated[str, StringConstraints(max_length=MAX_TEXT)] | None = Field(
        default=None, description='words and "quoted phrases"; misspellings are tolerated')
    meaning: bool = Field(default=False, description=(
        "with text: also find the words the text means (\"something to drink\": beverage, "
        "juice, milk), ranked after exact words"))
    region: Annotated[list[Name], BeforeValidator(listed), Field(max_length=MAX_LIST)] = Field(
        default=[], description="region names (any of them)")
    labelled: Annotated[list[Name], BeforeValidator(listed), Field(max_length=MAX_LIST)] = Field(
        default=[], description="labels any annotation gave (any of them), exactly, case and "
                                "word separators aside: cereal, SiggBottle = sigg bottle")
    robot: Annotated[list[Name], BeforeValidator(listed), Field(max_length=MAX_LIST)] = Field(
        default=[], description="robot names (any of them)")
    map: Annotated[list[Name], BeforeValidator(listed), Field(max_length=MAX_LIST)] = Field(
        default=[], description="maps (any of them): positions, boxes and spheres are in one "
                                "map's frame")
    object: Annotated[list[Id], BeforeValidator(listed), Field(max_length=MAX_LIST)] = Field(
        default=[], description="object ids (any of them)")
    box: Box | None = Field(default=None, description="x0,y0,z0,x1,y1,z1 in the map frame")
    sphere: Sphere | None = Field(default=None, description="x,y,z,radius in the map frame")
    after: Time | None = Field(default=None, description="at or after this time")
    before: Time | None = Field(default=None, description="at or before this time")
    at: Time | None = Field(default=None, description="exactly at this time (a scene's)")
    where: Annotated[list[Predicate], BeforeValidator(listed),
                     Field(max_length=MAX_PREDICATES)] = Field(
        default=[], description="annotation field predicates, type:field<op>value (all hold)")

    @model_validator(mode="after")
    def _consistent(self):
        if self.at is not None and (self.after is not None or self.before is not None):
            raise ValueError("give `at`, or `after` and/or `before`, not both")
        in_order(self.after, self.before)
        if self.meaning and not self.text:
            raise ValueError("meaning needs text")
        if self.text is not None and len(words(self.text)) > MAX_WORDS:
            raise ValueError(f"the text has more than {MAX_WORDS} words")
        return self


class ClusterQuery(ClusterFilter):
    """Clusters matching a filter, a page at a time (or the k nearest to a point)."""

    near: Point | None = Field(default=None, description="x,y,z: the k nearest to this point")
    k: Annotated[int, Field(ge=1, le=MAX_K)] = Field(default=10, description="with near")
    sort: Sort | None = Field(
        default=None, description="newest (default), oldest, relevance (default with text), "
                                  "distance (with near, the only one)")
    limit: Annotated[int, Field(ge=0, le=MAX_PAGE)] = Field(
        default=50, description="page size; 0 with count: the count alone, no page read")
    cursor: Annotated[str, StringConstraints(max_length=400)] | None = Field(
        default=None, description="`next` of the previous page")
    count: bool = Field(default=False, description="also count every match")

    @model_validator(mode="after")
    def _sorted(self):
        sort = self.sort or ("distance" if self.near else "relevance" if self.text else "newest")
        if (sort == "distance") != (self.near is not None):
            raise ValueError("sort=distance goes with near, and near sorts by distance only")
        if sort == "relevance" and not self.text:
            raise ValueError("sort=relevance needs text")
        if self.near is not None and self.cursor is not None:
            raise ValueError("the k nearest come in one page: no cursor")
        if self.limit == 0 and not (self.count and self.near is None):
            raise ValueError("limit=0 asks for no page: with count=true it asks for the count "
                             "alone (not of the k nearest)")
        object.__setattr__(self, "sort", sort)
        return self

    def filter_part(self) -> ClusterFilter:
        return ClusterFilter(**{name: getattr(self, name) for name in ClusterFilter.model_fields})


# --- questions ------------------------------------------------------------------------------

Subject = Annotated[str, StringConstraints(min_length=1, max_length=MAX_TEXT)]


class About(Strict):
    """An object named by text ("the ketchup", misspellings tolerated), an object id or a
    cluster id (the object that observation is believed to be)."""

    x: Subject = Field(description="text, object id or cluster id")
    limit: Annotated[int, Field(ge=1, le=MAX_ANSWERS)] = Field(
        default=5, description="how many candidate objects, best first")
    map: Name | None = Field(default=None, description="the map (default: every map)")


class Window(Strict):
    """A question with a time window (`after`, `before`: its own last fields, so that the
    engine's methods take the subject first), its ends in order when both are given."""

    @model_validator(mode="after")
    def _in_order(self):
        in_order(self.after, self.before)
        return self


class History(About, Window):
    after: Time | None = None
    before: Time | None = None


def in_order(after: int | None, before: int | None) -> None:
    """A time window's ends, when both are given, in order."""
    if None not in (after, before) and after > before:
        raise ValueError("`after` is later than `before`")


class Place(Strict):
    """A region by name, or a volume, in one map or in every map; or a whole map."""

    map: Name | None = Field(default=None, description="the map (default: every map)")
    region: Name | None = None
    box: Box | None = None
    sphere: Sphere | None = None

    @model_validator(mode="after")
    def _one_place(self):
        places = sum(v is not None for v in (self.region, self.box, self.sphere))
        if places > 1 or (places == 0 and self.map is None):
            raise ValueError("give one place: region, box or sphere, or a whole map")
        return self


class AtTime(Place):
    t: Time | None = Field(default=None, description="the moment (default: now)")


class Between(Place):
    t1: Time
    t2: Time | None = Field(default=None, description="default: now")

    @model_validator(mode="after")
    def _ordered(self):
        if self.t2 is not None and self.t2 < self.t1:
            raise ValueError("t2 is before t1")
        if self.t2 is None and self.t1 > time.time_ns():
            raise ValueError("t1 is later than now (t2's default)")
        return self


class Cooccurrence(Window):
    """Where objects are seen, how often (and at what hour of the day, UTC)."""

    x: Subject | None = Field(default=None, description="one object (text or id); all if unset")
    by_hour: bool = False
    after: Time | None = None
    before: Time | None = None


class Timings(Window):
    """Per-annotator durations and problems, from the scenes' logs."""

    robot: Name | None = None
    after: Time | None = None
    before: Time | None = None


MAX_WINDOW = 5000


class AnnotatorWindow(Strict):
    """The latest scenes (of a robot) at or before a moment: what an annotator report sums up.
    A count of scenes, not a time span, so that its cost is bounded however busy the robots."""

    scenes: Annotated[int, Field(ge=1, le=MAX_WINDOW)] = Field(
        default=500, description="how many of the latest scenes")
    robot: Name | None = None
    before: Time | None = Field(default=None, description=(
        "the window's newest scene is at or before this time (default: now)"))


class ConfusionCell(AnnotatorWindow):
    """One cell of a confusion table: the clusters of the window on which `annotator` said
    `said` and `reference` (another annotator, or "(ground truth)") said `expected`; a class
    left out means that one said nothing."""

    annotator: Name
    reference: Name
    said: Name | None = None
    expected: Name | None = None
    limit: Annotated[int, Field(ge=1, le=MAX_PAGE)] = Field(default=100, description=(
        "how many clusters, newest first"))

    @model_validator(mode="after")
    def _a_cell(self):
        if self.annotator == self.reference:
            raise ValueError("annotator and reference must differ")
        if self.said is None and self.expected is None:
            raise ValueError("give said, expected or both: no cell holds clusters neither "
                             "classified")
        return self


Step = Literal["at", "first", "previous", "next", "last", "event", "failure",
               "previous_failure"]


class Playback(Strict):
    """A robot's scenes as a sequence: the scene at a moment, or a step from it."""

    robot: Name
    map: Name | None = Field(default=None, description=(
        "only the robot's scenes in this map (default: in every map)"))
    t: Time | None = Field(default=None, description="the moment (default: now)")
    step: Step = Field(default="at", description=(
        "at: the scene at or before t (the first, before it); first, previous, next, last; "
        "event: the next scene after t with an event of `object`; failure: the next scene "
        "after t where an annotator failed (an error line in its log); previous_failure: the "
        "one before"))
    object: Id | None = Field(default=None, description="with step=event: the object")

    @model_validator(mode="after")
    def _object_with_event(self):
        if (self.step == "event") != (self.object is not None):
            raise ValueError("give object with step=event, and only then")
        return self
