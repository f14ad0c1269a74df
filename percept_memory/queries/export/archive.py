"""Where an export's entries go: a zip written as a stream of chunks, or a folder.

The zip is written with the standard library onto a sink that keeps only the bytes not yet
handed on, so it streams whatever its size; the list of entries the zip ends with waits on
disk, not in memory. Every header field is fixed (time 1980-01-01,
permissions, system), so the same entries give the same bytes. Images are stored as they are
(PNG is compressed already), text is deflated.

Entries whose content is known only at the end (COCO's annotation list, the provenance
sidecar) are gathered in spools: in memory up to a few MB, then in a temporary file.
"""

from __future__ import annotations

import json
import pickle
import re
import tempfile
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, Protocol

FIXED_TIME = (1980, 1, 1, 0, 0, 0)
SPOOL_MEMORY = 4 * 2**20
CHUNK = 2**20


class Archive(Protocol):
    def add(self, name: str, chunks: Iterable[bytes], size: int) -> None:
        """One entry of `size` bytes, given in chunks."""


UNSAFE = re.compile(r"[^\w.-]+")  # anything but letters, digits, _ . and -
DEVICES = re.compile(r"(?i)(con|prn|aux|nul|com\d|lpt\d)(\..*)?")  # Windows refuses these
NAME_CHARACTERS = 60  # at most 240 bytes in UTF-8: a file system's names take 255


def file_name(text: str) -> str:
    """A name as a part of an entry's path that every file system and unzip takes: unsafe
    characters (a /, a :, spaces) as _, no dot at either end, at most NAME_CHARACTERS, never
    a Windows device name (CON, NUL.txt). Different texts may give one name: callers that
    need them apart say so (ImageFolder's folders)."""
    safe = UNSAFE.sub("_", text).strip("._")[:NAME_CHARACTERS].strip("._") or "_"
    return f"_{safe}" if DEVICES.fullmatch(safe) else safe


def add_bytes(archive: Archive, name: str, data: bytes) -> None:
    archive.add(name, [data], len(data))


def add_json(archive: Archive, name: str, value: Any) -> None:
    add_bytes(archive, name, (json.dumps(value, indent=2, sort_keys=True) + "\n").encode())


class ZipArchive:
    """A zip on any writable binary stream. It is written as onto a stream that cannot seek
    (sizes and checksums after each entry), so a file gets the same bytes as a download."""

    def __init__(self, stream):
        self.zip = zipfile.ZipFile(_WriteOnly(stream), "w", allowZip64=True)
        self.zip.filelist = _EntriesOnDisk()  # what the central directory at the end lists
        self.zip.NameToInfo = _Forgetful()  # kept to warn of repeated names: ours are unique

    def add(self, name: str, chunks: Iterable[bytes], size: int) -> None:
        info = zipfile.ZipInfo(name, FIXED_TIME)
        info.create_system = 3  # unix
        info.external_attr = 0o644 << 16
        info.compress_type = zipfile.ZIP_STORED if name.endswith(".png") else \
            zipfile.ZIP_DEFLATED
        info.file_size = size  # lets zipfile choose zip64 headers up front
        with self.zip.open(info, "w", force_zip64=size >= zipfile.ZIP64_LIMIT) as entry:
            for chunk in chunks:
                entry.write(chunk)

    def close(self) -> None:
        self.zip.close()

    def abandon(self) -> None:
        """An export that failed: no end of the zip is written (zipfile would, when collected,
        onto a file closed by then: a traceback on Ctrl-C)."""
        self.zip.fp = None


class FolderArchive:
    """Entries as files under a folder (Export.save: a new one)."""

    def __init__(self, root: Path):
        self.root = root

    def add(self, name: str, chunks: Iterable[bytes], size: int) -> None:
        path = self.root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as file:
            for chunk in chunks:
                file.write(chunk)

    def close(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)  # an export of nothing is an empty folder

    def abandon(self) -> None:
        """(Export.save removes the folder.)"""


class _EntriesOnDisk(list):
    """zipfile keeps every entry's ZipInfo until it writes the central directory at the end:
    some 400 bytes an entry, 40 MB for 100,000 crops. This list keeps them in a temporary
    file instead, so memory does not grow with the number of entries."""

    def __init__(self):
        super().__init__()
        self.file = tempfile.TemporaryFile()  # noqa: SIM115 (closed once read)
        self.count = 0

    def append(self, info: zipfile.ZipInfo) -> None:
        pickle.dump(info, self.file)
        self.count += 1

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[zipfile.ZipInfo]:
        self.file.seek(0)
        for _ in range(self.count):
            yield pickle.load(self.file)
        self.file.close()


class _Forgetful(dict):
    def __setitem__(self, key, value) -> None:
        pass


class _WriteOnly:
    def __init__(self, stream):
        self.stream = stream

    def write(self, data) -> int:
        return self.stream.write(data)

    def flush(self) -> None:
        self.stream.flush()


class ChunkSink:
    """A write-only stream that hands its bytes on: `drain()` gives what was written since,
    in chunks of up to 1 MB. What waits is spooled (the zip's central directory, written in
    one go at the end, is some 100 bytes an entry)."""

    def __init__(self):
        self.file = tempfile.SpooledTemporaryFile(max_size=SPOOL_MEMORY)  # noqa: SIM115

    def write(self, data) -> int:
        return self.file.write(data)

    def flush(self) -> None:
        pass

    def drain(self) -> Iterator[bytes]:
        self.file.seek(0)
        while chunk := self.file.read(CHUNK):
            yield chunk
        self.file.seek(0)
        self.file.truncate()


class Spool:
    """Bytes gathered for an entry written at the end."""

    def __init__(self):
        self.file = tempfile.SpooledTemporaryFile(max_size=SPOOL_MEMORY)  # noqa: SIM115 (closed once read)
        self.size = self.items = 0

    def write(self, data: bytes) -> None:
        self.file.write(data)
        self.size += len(data)

    def line(self, value: Any) -> None:
        """One JSON line (keys sorted: the same value gives the same bytes)."""
        self.write(_json(value) + b"\n")
        self.items += 1

    def item(self, value: Any) -> None:
        """One element of a JSON array (the brackets are the caller's)."""
        self.write((b"," if self.items else b"") + _json(value))
        self.items += 1

    def chunks(self) -> Iterator[bytes]:
        self.file.seek(0)
        while chunk := self.file.read(CHUNK):
            yield chunk
        self.file.close()


def _json(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":")).encode()
