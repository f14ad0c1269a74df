"""Large binary values leave the document: the converter hands them to the store as blobs.

The converter does no I/O. While encoding, every binary value above the threshold is replaced
by a reference `{"_blob": <sha256>, "size": n}` and collected in `EncodeContext.blobs`; the
store keeps those apart from the documents (memory/documents.py: blob_homes). While decoding,
the store passes the blobs it fetched in `DecodeContext.blobs`. Blob ids are content hashes,
so a retried write stores nothing twice.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field

DEFAULT_THRESHOLD = 128 * 1024
BLOB_KEY = "_blob"


def content_id(data: bytes) -> str:
    """The id of a blob: its SHA-256, so equal bytes are stored once."""
    return "sha256:" + hashlib.sha256(data).hexdigest()


class ConversionError(ValueError):
    """A value cannot be converted; the message names the field path and the problem."""


@dataclass
class EncodeContext:
    """What one encoding produced besides the document: blobs to store, type names used."""

    threshold: int = DEFAULT_THRESHOLD
    blobs: dict[str, bytes] = field(default_factory=dict)
    type_names: set[str] = field(default_factory=set)

    def binary(self, data: bytes) -> bytes | dict:
        """`data` itself, or a reference to it once it is above the threshold."""
        if len(data) <= self.threshold:
            return data
        blob_id = content_id(data)
        self.blobs[blob_id] = data
        return {BLOB_KEY: blob_id, "size": len(data)}


@dataclass
class DecodeContext:
    blobs: Mapping[str, bytes] = field(default_factory=dict)

    def binary(self, value: bytes | dict) -> bytes:
        """The bytes of an inline binary value or of a blob reference."""
        if isinstance(value, bytes):
            return value
        if isinstance(value, dict) and BLOB_KEY in value:
            try:
                return self.blobs[value[BLOB_KEY]]
            except KeyError:
                raise ConversionError(f"blob {value[BLOB_KEY]} was not loaded") from None
        raise ConversionError(f"expected binary data, got {type(value).__name__}")

