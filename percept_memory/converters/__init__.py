"""Type-driven codec between model objects and BSON documents. No I/O, no MongoDB client."""

import numpy as np

from .arrays import NDArrayCodec
from .blobs import BLOB_KEY, ConversionError, DecodeContext, EncodeContext, content_id
from .codec import (
    MAX_TYPE_NAME,
    TYPE_KEY,
    ForeignCodec,
    Unknown,
    decode,
    encode,
    escape_key,
    foreign_codec_names,
    register_codec,
    unescape_key,
)
from .images import ImageCodec
from .registry import (
    Typed,
    aliases_of,
    class_for,
    name_of,
    register_type,
    registered_types,
    reserve_namespace,
)

register_codec(np.ndarray, NDArrayCodec())

__all__ = [
    "BLOB_KEY",
    "MAX_TYPE_NAME",
    "TYPE_KEY",
    "ConversionError",
    "DecodeContext",
    "EncodeContext",
    "ForeignCodec",
    "ImageCodec",
    "Typed",
    "Unknown",
    "aliases_of",
    "class_for",
    "content_id",
    "decode",
    "encode",
    "escape_key",
    "foreign_codec_names",
    "name_of",
    "register_codec",
    "register_type",
    "registered_types",
    "reserve_namespace",
    "unescape_key",
]
