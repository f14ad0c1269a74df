"""The base of every stored type: a pydantic model with a stable `_type` name and an id."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any

import numpy as np
from bson import ObjectId
from pydantic import (
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    WithJsonSchema,
    model_validator,
)

from percept_memory.converters import Typed, class_for, name_of, register_type

stored_type = register_type
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

Timestamp = Annotated[
    int,
    Field(ge=0, lt=2**63, description="nanoseconds since the Unix epoch, UTC"),
]
"""Exact time of a percept: int64 nanoseconds, as RoboSherlock stored it."""


def timestamp_from_datetime(moment: datetime) -> int:
    """Nanoseconds since the epoch of a timezone-aware datetime (naive means UTC)."""
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    delta = moment - datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


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
    def _dispatch_on_type(cls, data: Any, handler):
        if isinstance(data, dict) and "_type" in data:
            data = dict(data)
            name = data.pop("_type")
            target = class_for(name) if isinstance(name, str) else None
            if target is None or not issubclass(target, cls):
                raise ValueError(f"_type {name!r} is not a registered kind of {cls.__name__}")
            if target is not cls:
                return target.model_validate(data)
        return handler(data)

    @property
    def type_name(self) -> str:
        """The stable name this object is stored under."""
        return name_of(type(self))

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(
            _same(self.__dict__[name], other.__dict__[name]) for name in type(self).model_fields
        ) and _same(self._unknown_fields or {}, other._unknown_fields or {})

    __hash__ = None  # type: ignore[assignment]


class Identifiable(Model):
    """Carries an id that is assigned on first store and never changes (thesis 3.2.1.3), so an
    object that went through more annotators later updates the stored one in place."""

    id: Id | None = Field(default=None, alias="_id")

    def ensure_id(self) -> ObjectId:
        """The object's id, assigning a new one if it has none yet."""
        if self.id is None:
            self.id = ObjectId()
        return self.id
