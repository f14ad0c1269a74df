"""The generic codec: model objects <-> BSON-ready documents, driven by type annotations.

Written once for every present and future type (thesis 3.2.1.3: "a generic, templated set of
classes to offer fully automatic conversion between all types, present and future, and
MongoDB"). For each registered class a plan is compiled from its field annotations the first
time it is used; values whose annotation needs no conversion (str, int, float, bool, ObjectId,
...) are copied without a function call, which keeps the codec fast.

Types the annotations cannot describe (numpy arrays, images) get a foreign codec, registered
once per Python type with `register_codec` (thesis 3.1.2, FeatureStructureConversion).
"""

from __future__ import annotations

import enum
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Protocol

from bson import ObjectId
from pydantic import BaseModel, SerializationInfo, model_serializer, model_validator

from .blobs import ConversionError, DecodeContext, EncodeContext
from .extended_json import from_extended_json, to_extended_json
from .registry import Typed, class_for, close_names, is_reserved, name_of

TYPE_KEY = "_type"
TYPE_NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*", re.ASCII)
"""A type name is a dotted identifier (`lab.annotation.Weight`): the types catalogue and the
search keys use it as a key, so no `$`, path or empty name gets there."""
MAX_TYPE_NAME = 200


class ForeignCodec(Protocol):
    """Conversion of one Python type that is not described by field annotations alone."""

    name: str  # written as `_type`, so tagged values decode without an annotation

    def encode(self, value: Any, ctx: EncodeContext) -> dict: ...

    def decode(self, doc: dict, ctx: DecodeContext) -> Any: ...


_foreign_by_class: dict[type, ForeignCodec] = {}
_foreign_by_name: dict[str, ForeignCodec] = {}


def register_codec(cls: type, codec: ForeignCodec) -> None:
    """Use `codec` for every value of type `cls` (exactly that type)."""
    _foreign_by_class[cls] = codec
    _foreign_by_name[codec.name] = codec
    _field_codecs.clear()


def foreign_codec_names() -> set[str]:
    """The `_type` names written by foreign codecs (e.g. "ndarray")."""
    return set(_foreign_by_name)


class Unknown(Typed):
    """A stored object whose `_type` this program does not know (or cannot read).

    `fields` is the stored document as it was read, `_type` where it stood, and it writes
    back unchanged, so data written by a newer version, or by RoboSherlock, is never lost.
    In JSON, the BSON values JSON has no type for are MongoDB Extended JSON (extended_json.py).
    """

    type_name: str
    fields: dict[str, Any]
    problem: str | None = None  # why a known type could not be read, if that is the case

    @model_validator(mode="before")
    @classmethod
    def _from_document(cls, data: Any) -> Any:
        """A plain document with an unregistered `_type` (from JSON) is kept as it is, its
        Extended JSON values read as the BSON values they stand for."""
        if not isinstance(data, Mapping) or TYPE_KEY not in data or "fields" in data:
            return data
        name = data[TYPE_KEY]
        if not isinstance(name, str) or class_for(name) is not None:
            raise ValueError(f"{TYPE_KEY} {name!r} is a registered type; its fields do not fit")
        if TYPE_NAME.fullmatch(name) and "." not in name:  # a short name: whose type?
            hint = close_names(name)
            raise ValueError(f"{TYPE_KEY} {name!r} is not a type name: types are named in full, "
                             "with their namespace, such as 'lab.annotation.Weight'"
                             + (f"; did you mean {hint[0]!r}?" if hint else ""))
        if not TYPE_NAME.fullmatch(name) or len(name) > MAX_TYPE_NAME:
            raise ValueError(f"{TYPE_KEY} {name[:MAX_TYPE_NAME]!r} is not a type name: a dotted "
                             f"identifier such as 'lab.annotation.Weight', at most "
                             f"{MAX_TYPE_NAME} characters")
        if is_reserved(name):
            hint = close_names(name)
            raise ValueError(f"unknown type {name!r}" + (f"; did you mean {hint[0]!r}?" if hint
                                                          else ""))
        return {"type_name": name, "fields": from_extended_json(dict(data))}

    @model_validator(mode="after")
    def _fields_carry_the_type(self) -> Unknown:
        if self.fields.get(TYPE_KEY) != self.type_name:
            self.fields = {TYPE_KEY: self.type_name, **self.fields}
        return self

    @model_serializer
    def _as_stored(self, info: SerializationInfo) -> dict:
        return to_extended_json(self.fields) if info.mode_is_json() else self.fields


# --- encoding and decoding of tagged documents --------------------------------------------


def encode(value: Typed, ctx: EncodeContext | None = None) -> dict:
    """A registered model object as a document ready for `bson.encode` / pymongo."""
    return _encode_object(value, ctx or EncodeContext())


def decode(doc: Mapping, ctx: DecodeContext | None = None) -> Any:
    """The object a tagged document describes; `Unknown` when its `_type` is not registered."""
    return _decode_tagged(doc, ctx or DecodeContext())


def _encode_object(value: Any, ctx: EncodeContext) -> dict:
    cls = type(value)
    foreign = _foreign_by_class.get(cls)
    if foreign is not None:
        ctx.type_names.add(foreign.name)
        return foreign.encode(value, ctx)
    if cls is Unknown:
        ctx.type_names.add(value.type_name)
        return _encode_unknown(value)
    plan = _plan(cls)
    ctx.type_names.add(plan.name)
    return plan.encode(value, ctx)


def _decode_tagged(doc: Mapping, ctx: DecodeContext) -> Any:
    if not isinstance(doc, Mapping) or TYPE_KEY not in doc:
        raise ConversionError(f"expected a document with {TYPE_KEY!r}, got {_describe(doc)}")
    name = doc[TYPE_KEY]
    foreign = _foreign_by_name.get(name)
    if foreign is not None:
        return foreign.decode(doc, ctx)
    cls = class_for(name)
    if cls is None:
        return Unknown.model_construct(type_name=name, fields=dict(doc))
    try:
        return _plan(cls).decode(doc, ctx)
    except ConversionError as error:
        # Reading never crashes: keep what is stored, say why it could not be read.
        return Unknown.model_construct(type_name=name, fields=dict(doc), problem=str(error))


def _encode_unknown(value: Unknown) -> dict:
    """The stored document again, byte for byte: `_type` keeps its place among the fields."""
    if TYPE_KEY not in value.fields:
        return {TYPE_KEY: value.type_name, **value.fields}
    doc = dict(value.fields)
    doc[TYPE_KEY] = value.type_name
    return doc


def _describe(value: Any) -> str:
    return type(value).__name__


# --- per-class plans ------------------------------------------------------------------------


class _Plan:
    """How to encode and decode one registered class, compiled from its annotations.

    Each field is a tuple (document key, attribute, encoder, decoder, required); a None
    encoder or decoder means the value is stored as it is.
    """

    def __init__(self, cls: type[Typed]):
        name = name_of(cls)
        if name is None:
            raise ConversionError(
                f"{cls.__qualname__} is not a registered type; decorate it with register_type"
            )
        self.cls = cls
        self.name = name
        self.fields = []
        for attr, info in cls.model_fields.items():
            codec = _codec_for(info.annotation)
            key = info.alias or attr
            self.fields.append((key, attr, codec.encode, codec.decode, info.is_required()))
        self.keys = frozenset(field[0] for field in self.fields) | {TYPE_KEY}

    def encode(self, obj: Typed, ctx: EncodeContext) -> dict:
        doc: dict[str, Any] = {TYPE_KEY: self.name}
        values = obj.__dict__
        for key, attr, encoder, _, _ in self.fields:
            value = values[attr]
            if encoder is None or value is None:
                doc[key] = value
                continue
            try:
                doc[key] = encoder(value, ctx)
            except (ConversionError, TypeError, ValueError) as error:
                raise ConversionError(f"{self.name}.{key}: {error}") from error
        if unknown := obj.unknown_fields():
            for key, value in unknown.items():
                doc.setdefault(key, value)
        return doc

    def decode(self, doc: Mapping, ctx: DecodeContext) -> Typed:
        values: dict[str, Any] = {}
        for key, attr, _, decoder, required in self.fields:
            if key not in doc:
                if required:
                    raise ConversionError(f"{self.name}: required field {key!r} is missing")
                continue
            value = doc[key]
            if decoder is None or value is None:
                values[attr] = value
                continue
            try:
                values[attr] = decoder(value, ctx)
            except (ConversionError, TypeError, ValueError, KeyError) as error:
                raise ConversionError(f"{self.name}.{key}: {error}") from error
        obj = self.cls.model_construct(**values)
        if len(doc) > len(values) + 1:
            unknown = {k: v for k, v in doc.items() if k not in self.keys}
            if unknown:
                obj.keep_unknown_fields(unknown)
        return obj


_plans: dict[type, _Plan] = {}


def _plan(cls: type) -> _Plan:
    plan = _plans.get(cls)
    if plan is None:
        plan = _plans[cls] = _Plan(cls)
    return plan


# --- field codecs, one per annotation -------------------------------------------------------

Encoder = Callable[[Any, EncodeContext], Any]
Decoder = Callable[[Any, DecodeContext], Any]


@dataclass(frozen=True, slots=True)
class FieldCodec:
    """Conversion of the values of one annotation. `None` en/decoder: stored as they are."""

    encode: Encoder | None
    decode: Decoder | None
    owns: Callable[[Any], bool]  # is this Python value one of ours (to pick a Union arm)?
    accepts: Callable[[Any], bool]  # is this stored value one of ours (to pick a Union arm)?


_field_codecs: dict[Any, FieldCodec] = {}

_AS_STORED = (str, int, float, bool, bytes, ObjectId, type(None))


def _codec_for(annotation: Any) -> FieldCodec:
    try:
        return _field_codecs[annotation]
    except KeyError:
        codec = _field_codecs[annotation] = _build_codec(annotation)
        return codec
    except TypeError:  # unhashable annotation metadata
        return _build_codec(annotation)


BARE = {list: list[Any], tuple: tuple[Any, ...], set: set[Any], dict: dict[str, Any]}
"""A container annotated without its items' types, as the annotated one it stands for."""


def _build_codec(annotation: Any) -> FieldCodec:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _codec_for(args[0])
    if annotation is Any or annotation is object:
        return FieldCodec(_encode_any, _decode_any, lambda v: True, lambda v: True)
    if origin is typing.Literal:
        allowed = set(args)
        return FieldCodec(None, None, lambda v: v in allowed, lambda v: v in allowed)
    if origin in (typing.Union, types.UnionType):
        return _union_codec(args)
    if origin in (list, Sequence, set, frozenset):
        item = _codec_for(args[0]) if args else _codec_for(Any)
        return _sequence_codec(item, list if origin is Sequence else origin)
    if origin is tuple:
        return _tuple_codec(args)
    if origin in (dict, Mapping):
        return _dict_codec(_codec_for(args[1]) if args else _codec_for(Any))
    if annotation in BARE:
        return _codec_for(BARE[annotation])
    if isinstance(annotation, type):
        return _class_codec(annotation)
    raise ConversionError(f"cannot store values annotated {annotation!r}")


def _class_codec(cls: type) -> FieldCodec:
    if cls is float:
        return FieldCodec(
            None, None, lambda v: isinstance(v, float), lambda v: isinstance(v, (float, int))
        )
    if cls is datetime:
        return FieldCodec(None, _decode_datetime, _isinstance(datetime), _isinstance(datetime))
    if issubclass(cls, enum.Enum):
        values = {member.value for member in cls}
        return FieldCodec(
            lambda v, ctx: v.value,
            lambda v, ctx: cls(v),
            _isinstance(cls),
            lambda v: v in values,
        )
    if issubclass(cls, _AS_STORED):
        return FieldCodec(None, None, _isinstance(cls), _isinstance(cls))
    foreign = _foreign_by_class.get(cls)
    if foreign is not None:
        return FieldCodec(
            _encode_object,
            foreign.decode,
            _isinstance(cls),
            lambda v: isinstance(v, Mapping) and v.get(TYPE_KEY) == foreign.name,
        )
    if issubclass(cls, BaseModel):
        return FieldCodec(
            _encode_object,
            _decode_tagged,
            _isinstance(BaseModel),
            lambda v: isinstance(v, Mapping) and TYPE_KEY in v,
        )
    raise ConversionError(f"no codec for {cls.__qualname__}; register one with register_codec")


def _isinstance(cls: type) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, cls)


def _decode_datetime(value: datetime, ctx: DecodeContext) -> datetime:
    return value if value.tzinfo else value.replace(tzinfo=UTC)


def _union_codec(arms: tuple) -> FieldCodec:
    codecs = [_codec_for(arm) for arm in arms if arm is not type(None)]
    if len(codecs) == 1:  # Optional[X]: None is stored as None by the plans
        return codecs[0]
    owns = lambda v: any(c.owns(v) for c in codecs)  # noqa: E731
    accepts = lambda v: any(c.accepts(v) for c in codecs)  # noqa: E731
    if all(c.encode is None and c.decode is None for c in codecs):
        return FieldCodec(None, None, owns, accepts)
    if all(c.encode is _encode_object for c in codecs):  # stored types: dispatch on `_type`
        return FieldCodec(_encode_object, _decode_tagged, owns, accepts)

    def encode_union(value, ctx):
        for c in codecs:
            if c.owns(value):
                return value if c.encode is None else c.encode(value, ctx)
        raise ConversionError(f"{_describe(value)} matches no type of {arms}")

    def decode_union(value, ctx):
        for c in codecs:
            if c.accepts(value):
                return value if c.decode is None else c.decode(value, ctx)
        raise ConversionError(f"stored {_describe(value)} matches no type of {arms}")

    return FieldCodec(encode_union, decode_union, owns, accepts)


_PYTHON_SEQUENCES = {
    list: (list, tuple), tuple: (tuple,), set: (set, frozenset), frozenset: (set, frozenset)
}


def _sequence_codec(item: FieldCodec, make: type) -> FieldCodec:
    """list[X], tuple[X, ...], set[X], frozenset[X]: a BSON array, `make` on the way back."""
    enc, dec = item.encode, item.decode
    owns, accepts = _isinstance(_PYTHON_SEQUENCES[make]), _isinstance(list)
    if enc is None and dec is None and make is list:
        return FieldCodec(None, None, owns, accepts)
    return FieldCodec(
        (lambda v, ctx: list(v)) if enc is None
        else lambda v, ctx: [x if x is None else enc(x, ctx) for x in v],
        (lambda v, ctx: make(v)) if dec is None
        else lambda v, ctx: make(x if x is None else dec(x, ctx) for x in v),
        owns,
        accepts,
    )


def _tuple_codec(args: tuple) -> FieldCodec:
    if len(args) == 2 and args[1] is Ellipsis:
        return _sequence_codec(_codec_for(args[0]), tuple)
    items = [_codec_for(arg) for arg in args]
    if all(c.encode is None and c.decode is None for c in items):
        return FieldCodec(
            lambda v, ctx: list(v), lambda v, ctx: tuple(v), _isinstance(tuple), _isinstance(list)
        )

    def encode_tuple(value, ctx):
        if len(value) != len(items):
            raise ConversionError(f"expected {len(items)} values, got {len(value)}")
        return [x if c.encode is None or x is None else c.encode(x, ctx)
                for c, x in zip(items, value, strict=True)]

    def decode_tuple(value, ctx):
        if len(value) != len(items):
            raise ConversionError(f"expected {len(items)} stored values, got {len(value)}")
        return tuple(x if c.decode is None or x is None else c.decode(x, ctx)
                     for c, x in zip(items, value, strict=True))

    return FieldCodec(encode_tuple, decode_tuple, _isinstance(tuple), _isinstance(list))


# MongoDB field names may not start with "$" and "." means a path: such keys are %-escaped.
_ESCAPES = {"%": "%25", ".": "%2E", "$": "%24", "\x00": "%00"}
_UNESCAPES = {v: k for k, v in _ESCAPES.items()}
_ESCAPED = re.compile("|".join(_UNESCAPES))
_NEEDS_ESCAPE = re.compile("[%.$\x00]")


def escape_key(key: str) -> str:
    if not isinstance(key, str):
        raise ConversionError(f"dictionary keys must be strings, got {_describe(key)}")
    if _NEEDS_ESCAPE.search(key):
        return _NEEDS_ESCAPE.sub(lambda match: _ESCAPES[match.group(0)], key)
    return key


def unescape_key(key: str) -> str:
    if "%" not in key:
        return key
    return _ESCAPED.sub(lambda match: _UNESCAPES[match.group(0)], key)


def _dict_codec(value_codec: FieldCodec) -> FieldCodec:
    enc, dec = value_codec.encode, value_codec.decode
    return FieldCodec(
        lambda v, ctx: {
            escape_key(k): (x if enc is None or x is None else enc(x, ctx)) for k, x in v.items()
        },
        lambda v, ctx: {
            unescape_key(k): (x if dec is None or x is None else dec(x, ctx)) for k, x in v.items()
        },
        _isinstance(dict),
        lambda v: isinstance(v, Mapping) and TYPE_KEY not in v,
    )


# --- values annotated Any: converted by what they are ---------------------------------------


def _encode_any(value: Any, ctx: EncodeContext) -> Any:
    if isinstance(value, (*_AS_STORED, datetime)):
        return value
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, BaseModel) or type(value) in _foreign_by_class:
        return _encode_object(value, ctx)
    if isinstance(value, (list, tuple, set, frozenset)):
        return [_encode_any(x, ctx) for x in value]
    if isinstance(value, Mapping):
        return {escape_key(k): _encode_any(x, ctx) for k, x in value.items()}
    raise ConversionError(f"cannot store a {_describe(value)}; register a codec for it")


def _decode_any(value: Any, ctx: DecodeContext) -> Any:
    if isinstance(value, list):
        return [_decode_any(x, ctx) for x in value]
    if isinstance(value, Mapping):
        if TYPE_KEY in value:
            return _decode_tagged(value, ctx)
        return {unescape_key(k): _decode_any(x, ctx) for k, x in value.items()}
    if isinstance(value, datetime):
        return _decode_datetime(value, ctx)
    return value
