"""The base of every stored type: a pydantic model with a stable `_type` name and an id."""

from __future__ import annotations

import re
import typing
from datetime import UTC, datetime
from typing import Annotated, Any

import numpy as np
from bson import ObjectId
from pydantic import (
    AfterValidator,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    GetJsonSchemaHandler,
    PlainSerializer,
    PlainValidator,
    SerializationInfo,
    SerializeAsAny,
    SerializerFunctionWrapHandler,
    StringConstraints,
    Tag,
    ValidationInfo,
    WithJsonSchema,
    model_serializer,
    model_validator,
)
from pydantic.fields import FieldInfo

from percept_memory.converters import (
    MAX_TYPE_NAME,
    Typed,
    Unknown,
    class_for,
    name_of,
    register_type,
    registered_types,
    reserve_namespace,
)

stored_type = register_type
reserve_namespace("pm.")  # our own type names: an unknown one is a typo, not foreign data
"""Class decorator naming a stored type: `@stored_type("pm.annotation.Shape", aliases=(...))`."""


def _to_object_id(value: Any) -> ObjectId:
    if isinstance(value, ObjectId):
        return value
    if isinstance(value, str) and ObjectId.is_valid(value):
        return ObjectId(value)
    raise ValueError(f"expected a 24-digit hex object id, got {value!r}")


Id = Annotated[
    ObjectId,
    PlainValidator(_to_object_id),
    PlainSerializer(str, when_used="json"),
    WithJsonSchema({"type": "string", "pattern": "^[0-9a-f]{24}$"}),
]
"""A MongoDB ObjectId; JSON carries it as 24 hex digits."""


def _an_integer(value: Any) -> Any:
    if isinstance(value, bool):  # an int to Python: `true` would be stored as 1 ns
        raise ValueError("a timestamp is an integer, not true or false")
    if isinstance(value, str):  # (pydantic would read "15..." as the number)
        raise ValueError("a timestamp is an integer of nanoseconds, not a string")
    if isinstance(value, float):  # a float holds 15-16 digits: 1.8e18 ns is 256 ns off
        raise ValueError("a timestamp is an integer of nanoseconds, not a number with a "
                         "point or an exponent (those lose the last digits)")
    return value


# what a terminal or a page acts on instead of showing: C0 and C1 controls (a newline, the
# escape sequences that clear a screen or write the clipboard) and the bidirectional overrides
CONTROLS = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")
MAX_NAME = 200  # characters of a name: a robot, map, region, annotator, class, image


def no_controls(text: str) -> str:
    if found := CONTROLS.search(text):
        raise ValueError(f"a name holds no control characters: {found[0]!r} at {found.start()}")
    return text


Name = Annotated[str, StringConstraints(max_length=MAX_NAME), AfterValidator(no_controls),
                 WithJsonSchema({"type": "string", "maxLength": MAX_NAME,
                                 "pattern": f"^[^{CONTROLS.pattern[1:-1]}]*$"})]
"""A name people read in lists, pages and the CLI: one line of at most MAX_NAME characters
(texts, such as OCR's or a log message, are not names)."""


def as_name(text: str) -> str:
    """A text made a name (what another program answered: a lookup's title as a brand): its
    control characters as spaces, its first MAX_NAME characters."""
    return CONTROLS.sub(" ", text)[:MAX_NAME]

MAX_TIMESTAMP = (2**63 - 1) // 10**9 * 10**9
"""2262-04-11T23:47:16Z, the last whole second int64 nanoseconds hold (pages round a time up
to whole seconds)."""

Timestamp = Annotated[
    int,
    BeforeValidator(_an_integer),
    Field(ge=0, le=MAX_TIMESTAMP, description="nanoseconds since the Unix epoch, UTC"),
    # (pydantic wrote ge and le, which are not JSON Schema, where it is optional)
    WithJsonSchema({"type": "integer", "minimum": 0, "maximum": MAX_TIMESTAMP,
                    "description": "nanoseconds since the Unix epoch, UTC"}),
]
"""Exact time of a percept: int64 nanoseconds, as RoboSherlock stored it (1970 to 2262)."""


def is_timestamp(field: FieldInfo) -> bool:
    """Whether a model's field is a Timestamp (shown as a time, not as its nanoseconds)."""
    return typing.get_args(Timestamp)[1] in field.metadata


def timestamp_from_datetime(moment: datetime) -> int:
    """Nanoseconds since the epoch of a timezone-aware datetime (naive means UTC)."""
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    delta = moment - datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


FRACTION = re.compile(r"(\d\d:\d\d:\d\d)[.,](\d+)")


def timestamp_from_iso(text: str) -> int:
    """Nanoseconds since the epoch of an ISO 8601 date or time (naive means UTC), every digit
    of its fraction of a second kept: a datetime keeps six, and a time printed to the
    nanosecond must find the scene it names. Raises ValueError."""
    text = text.strip()
    if text.endswith("z"):  # (RFC 3339 allows a lowercase one)
        text = text[:-1] + "Z"
    nanoseconds = 0
    if fraction := FRACTION.search(text):
        digits = fraction.group(2)
        if len(digits) > 9:
            raise ValueError(f"{text!r} has more digits than nanoseconds")
        nanoseconds = int(digits.ljust(9, "0"))
        text = text[:fraction.end(1)] + text[fraction.end(2):]
    return timestamp_from_datetime(datetime.fromisoformat(text)) + nanoseconds


def iso_from_timestamp(nanoseconds: int) -> str:
    """A timestamp in ISO 8601 UTC to the nanosecond, as timestamp_from_iso reads it back."""
    seconds = datetime.fromtimestamp(nanoseconds // 10**9, UTC).strftime("%Y-%m-%dT%H:%M:%S")
    return f"{seconds}.{nanoseconds % 10**9:09d}Z"


def datetime_from_timestamp(nanoseconds: int) -> datetime:
    """The UTC datetime of a timestamp (to the microsecond, all Python keeps)."""
    return datetime.fromtimestamp(nanoseconds // 1000 / 1_000_000, tz=UTC)


def _same(a: Any, b: Any) -> bool:
    """Equality that compares numpy arrays bit for bit (NaN == NaN, -0.0 != 0.0)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, float) and isinstance(b, float):
        both_nan = a != a and b != b
        return both_nan or (a == b and np.signbit(a) == np.signbit(b))
    return a == b


class Model(Typed):
    """A stored type. Input is validated strictly: unknown fields are an error, not ignored.

    A document with `_type` naming a registered subclass validates as that subclass, so a list
    of annotations read from JSON comes back as the right classes.
    """

    model_config = ConfigDict(
        extra="forbid",
        arbitrary_types_allowed=True,
        populate_by_name=True,
        validate_assignment=False,
        ser_json_inf_nan="constants",
    )

    @model_validator(mode="wrap")
    @classmethod
    def _dispatch_on_type(cls, data: Any, handler, info: ValidationInfo):
        if isinstance(data, dict) and ("_type" in data or _is_base(cls)):
            data = dict(data)
            name = data.pop("_type", None)
            target = class_for(name) if isinstance(name, str) else None
            if target is None or not issubclass(target, cls):
                kinds = sorted(name_of(t) for t in _registered_kinds(cls))
                raise ValueError(f"_type {name!r} is not a kind of {cls.__name__}: one of {kinds}")
            if target is not cls:
                return target.__pydantic_validator__.validate_python(data, context=info.context)
        return handler(data)

    @classmethod
    def __get_pydantic_json_schema__(cls, core_schema, handler: GetJsonSchemaHandler) -> dict:
        """Registered types name their `_type`; a base such as Annotation is one of its kinds."""
        if name_of(cls) is not None:
            return _with_type(handler(core_schema), name_of(cls), handler, required=False)
        return {"oneOf": [
            _with_type(handler(kind.__pydantic_core_schema__), name_of(kind), handler, True)
            for kind in _registered_kinds(cls)
        ]}

    @model_serializer(mode="wrap")
    def _tagged(self, handler: SerializerFunctionWrapHandler, info: SerializationInfo) -> Any:
        """Dumps carry `_type` first, so polymorphic lists read back as the right classes."""
        fields = handler(self)
        if info.mode_is_json():
            fields = self._json_fields(fields)
        return {"_type": self.type_name, **fields}

    def _json_fields(self, fields: dict) -> dict:
        """Hook for types whose JSON form differs from their fields (images travel as PNG)."""
        return fields

    @property
    def type_name(self) -> str:
        """The stable name this object is stored under."""
        return name_of(type(self))

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(
            _same(self.__dict__[name], other.__dict__[name]) for name in type(self).model_fields
        ) and _same(self.unknown_fields() or {}, other.unknown_fields() or {})

    __hash__ = None  # type: ignore[assignment]


def _with_type(schema: dict, name: str, handler: GetJsonSchemaHandler, required: bool) -> dict:
    target = handler.resolve_ref_schema(schema)
    target["properties"] = {"_type": {"const": name}, **target.get("properties", {})}
    if required:
        target["required"] = ["_type", *target.get("required", [])]
    return schema


def _is_base(cls: type) -> bool:
    """Whether cls is the unnamed base of registered kinds, e.g. Annotation."""
    return name_of(cls) is None and bool(_registered_kinds(cls))


def _registered_kinds(base: type) -> list[type]:
    return [kind for kind in registered_types().values() if issubclass(kind, base)]


def polymorphic(base: type) -> Any:
    """The type of a field holding any registered kind of `base`, chosen by its `_type`, or an
    Unknown when no class is registered under that `_type` (kept as it is, never dropped)."""

    def arm(value: Any) -> str:
        if isinstance(value, Unknown):
            return "unknown"
        name = value.get("_type") if isinstance(value, dict) else None
        return "unknown" if isinstance(name, str) and class_for(name) is None else "known"

    return Annotated[
        Annotated[SerializeAsAny[base], Tag("known")]
        | Annotated[Unknown, Tag("unknown"), WithJsonSchema(FOREIGN_SCHEMA)],
        Discriminator(arm),
    ]


FOREIGN_SCHEMA = {
    "type": "object", "required": ["_type"], "additionalProperties": True,
    "description": "another program's object (lab.annotation.Weight, RoboSherlock's rs.*): any "
                   "fields, kept as they are; values JSON has no type for as MongoDB Extended "
                   "JSON",
    "properties": {"_type": {"type": "string", "maxLength": MAX_TYPE_NAME,
                             "pattern": r"^(?!pm\.)[A-Za-z_]\w*(\.[A-Za-z_]\w*)+$"}}}
"""An Unknown as JSON brings it: the document itself, its `_type` a full name not ours (pm.)."""


class Identifiable(Model):
    """Carries an id that is assigned on first store and never changes (thesis 3.2.1.3), so an
    object that went through more annotators later updates the stored one in place."""

    id: Id | None = Field(default=None, alias="_id")

    def ensure_id(self) -> ObjectId:
        """The object's id, assigning a new one if it has none yet."""
        if self.id is None:
            self.id = ObjectId()
        return self.id
