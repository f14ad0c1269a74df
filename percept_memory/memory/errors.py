"""Errors of the memory, each saying what went wrong and what to do."""

from __future__ import annotations

from pydantic import ValidationError
from pymongo.errors import BulkWriteError, DocumentTooLarge, DuplicateKeyError, OperationFailure


def problems_line(error: ValidationError, whole: str = "input") -> str:
    """A validation error as one line for people: `field.path: problem; ...` (`whole` for
    one of the whole input), no input echoed, no link."""
    return "; ".join(f"{'.'.join(map(str, e['loc'])) or whole}: "
                     f"{e['msg'].removeprefix('Value error, ')}"
                     for e in error.errors(include_url=False, include_input=False))


class StoreError(RuntimeError):
    """A request the store cannot carry out."""


class NotFound(StoreError, KeyError):
    def __init__(self, kind: str, key: object, why: str = ""):
        super().__init__(f"no {kind} {key}" + (f": {why}" if why else ""))
        self.kind, self.key = kind, key

    def __str__(self) -> str:
        return self.args[0]


def require_replica_set(hello: dict) -> None:
    """Atomic scene writes need transactions, which need a replica set or a sharded cluster."""
    if hello.get("setName") or hello.get("msg") == "isdbgrid":
        return
    raise StoreError(
        "this MongoDB server is a standalone server; percept-memory needs a replica set "
        "(a single-node one is fine) for atomic scene writes: start mongod with "
        "--replSet rs0 and run rs.initiate() once, or unset MONGODB_URI to use the "
        "embedded mongod"
    )


class DuplicateId(StoreError):
    """An id in the write is already used by another document (stored, or in the write)."""


def duplicate_key(error: Exception) -> dict | None:
    """The clashing key of a duplicate-key failure ({field: value}), or None for other errors."""
    if isinstance(error, BulkWriteError):
        first = (error.details.get("writeErrors") or [{}])[0]
        return first.get("keyValue") if first.get("code") == 11000 else None
    if isinstance(error, DuplicateKeyError):
        return (error.details or {}).get("keyValue") or {"key": str(error)}
    return None


class SceneExists(DuplicateId):
    """Another scene of the robot at the timestamp is stored: a scene is named by its robot
    and time, so the same one sent again is a no-op, and a different one would be lost."""

    def __init__(self, robot: str, timestamp: int, in_batch: bool = False):
        where = ("two different scenes at timestamp {} in this batch" if in_batch
                 else "another scene stored at timestamp {}").format(timestamp)
        super().__init__(
            f"not stored: robot {robot!r} has {where} "
            "(a scene is named by its robot and time: the same scene sent again is stored "
            "once; a different one needs a time of its own)")
        self.key = (robot, timestamp, in_batch)

    def __reduce__(self):  # raised in an ingest worker process, re-raised in the server
        return SceneExists, self.key


class TypeHookFailed(StoreError):
    """An annotation type's own code (labels(), texts()) failed on an annotation: the data
    fits the class, the class cannot describe it (a bug of the type, named)."""


class Unavailable(StoreError):
    """No MongoDB server could be selected for a write (PMEM_MONGO_TIMEOUT_MS)."""


class TooLarge(StoreError):
    """A document is over MongoDB's 16 MB limit."""

    def __init__(self, threshold: int):
        super().__init__(
            "not stored: a scene or a cluster with its annotations would exceed MongoDB's 16 MB "
            "limit for one document; images and arrays over PMEM_GRIDFS_THRESHOLD "
            f"({threshold} bytes) go to GridFS, texts do not"
        )


BSON_OBJECT_TOO_LARGE = 10334
TRANSACTION_TOO_LARGE_FOR_CACHE = 388


def transaction_too_large(error: Exception) -> bool:
    """Did the server abort a transaction that outgrew its cache (a batch of big scenes on a
    small WiredTiger cache)?"""
    if not isinstance(error, OperationFailure):
        return False
    codes = {error.code} | {e.get("code") for e in (error.details or {}).get("writeErrors", ())}
    return TRANSACTION_TOO_LARGE_FOR_CACHE in codes


class TransactionTooLarge(StoreError):
    """One scene alone is more than the server's cache can hold in a transaction."""

    def __init__(self, threshold: int):
        super().__init__(
            "not stored: writing this scene needs more than the MongoDB server's cache can hold "
            "in one transaction; give mongod a bigger cache (PMEM_MONGOD_CACHE_GB for the "
            "embedded one, --wiredTigerCacheSizeGB otherwise) or store large images and "
            f"arrays in GridFS by setting PMEM_GRIDFS_THRESHOLD below {threshold} bytes"
        )


def too_large(error: Exception) -> bool:
    """Did the client or the server refuse a document for its size?"""
    if isinstance(error, DocumentTooLarge):
        return True
    return isinstance(error, OperationFailure) and error.code == BSON_OBJECT_TOO_LARGE


def redacted(uri: str) -> str:
    """A connection string fit to print: the password is replaced by ***."""
    scheme, sep, rest = uri.partition("://")
    credentials, at, hosts = rest.rpartition("@")
    if not at or ":" not in credentials:
        return uri
    return f"{scheme}{sep}{credentials.split(':', 1)[0]}:***@{hosts}"


def reason(error: Exception) -> str:
    """What pymongo says went wrong, without its dump of timeouts and topology."""
    return str(error).split(" (configured timeouts")[0]


def unreachable(uri: str, error: Exception) -> StoreError:
    """The database at `uri` could not be used at all."""
    return StoreError(
        f"cannot use MongoDB at {redacted(uri)}: {reason(error)}. Check MONGODB_URI, or unset "
        "it to use the embedded mongod"
    )
