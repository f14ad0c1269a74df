"""BSON values that JSON has no type for, written as MongoDB Extended JSON (relaxed).

What an `Unknown` keeps is a stored document as it was read: a RoboSherlock annotation holds
ObjectIds, bytes and 64-bit integers. In the interchange JSON each such value is the object
MongoDB's own tools write for it (`{"$oid": "..."}`, `{"$binary": {...}}`, ...; bson.json_util
does the work), and is read back as that value, so the annotation comes back unchanged. Only
the value types listed in WRAPPERS are read: JavaScript code, symbols and pointers, which BSON
has deprecated or which a database would run, are not.
"""

from __future__ import annotations

import json
from typing import Any

from bson import Int64, json_util
from bson.errors import BSONError

WRAPPERS = frozenset({
    "$oid", "$date", "$binary", "$uuid", "$numberDecimal", "$numberLong", "$numberInt",
    "$numberDouble", "$timestamp", "$regularExpression", "$minKey", "$maxKey"})
"""The first key of an Extended JSON value read back (see the module's docstring)."""
INTEGER_BITS = {"$numberInt": 32, "$numberLong": 64}  # (json_util reads any size)
MAX_DEPTH = 100  # MongoDB's: a document nested deeper is not stored


def to_extended_json(document: dict) -> dict:
    """The document with every value JSON cannot hold as its Extended JSON object; a 64-bit
    integer (Int64) too, which the relaxed form would write as a plain number, read back as a
    32-bit one where it fits."""
    return json.loads(json_util.dumps(_longs_kept(document),
                                      json_options=json_util.RELAXED_JSON_OPTIONS))


def _longs_kept(value: Any) -> Any:
    if isinstance(value, Int64):
        return {"$numberLong": str(int(value))}
    if isinstance(value, dict):
        return {key: _longs_kept(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_longs_kept(item) for item in value]
    return value


def extended_value(candidate: dict) -> tuple[bool, Any]:
    """(True, the BSON value) when the object is one Extended JSON value of WRAPPERS;
    (False, None) when it is not one at all. A malformed one raises ValueError naming it."""
    first = next(iter(candidate), None)
    if first not in WRAPPERS:
        return False, None
    try:
        value = json_util.object_hook(dict(candidate))
    except (BSONError, TypeError, ValueError, ArithmeticError, KeyError) as error:
        raise ValueError(f"not a MongoDB Extended JSON {first} value: {str(error)[:120]}"
                         ) from None
    if isinstance(value, dict):
        raise ValueError(f"not a MongoDB Extended JSON {first} value")
    bits = INTEGER_BITS.get(first)
    if bits and not -(2 ** (bits - 1)) <= value < 2 ** (bits - 1):
        raise ValueError(f"not a MongoDB Extended JSON {first} value: beyond {bits} bits")
    return True, value


def from_extended_json(value: Any, depth: int = MAX_DEPTH) -> Any:
    """The value with its Extended JSON objects read as the BSON values they stand for (read
    inside out, as bson.json_util does: `{"$date": {"$numberLong": ...}}`)."""
    if isinstance(value, list | dict) and depth <= 0:
        raise ValueError(f"nested deeper than MongoDB stores ({MAX_DEPTH} levels)")
    if isinstance(value, list):
        return [from_extended_json(item, depth - 1) for item in value]
    if not isinstance(value, dict):
        return value
    inner = {key: from_extended_json(item, depth - 1) for key, item in value.items()}
    found, bson_value = extended_value(inner)
    return bson_value if found else inner
