"""An export from start to end: select, label, write, and say what was left out.

    export = Export(store, ExportQuery(format="coco", region=["table"]))
    export.total                         # clusters selected, at most `limit` (the query is
                                         # checked here)
    for chunk in export.zip_stream(): ...  # the zip, a chunk at a time
    export.started()                     # the same, NothingExported if nothing would be in it
    export.save(Path("out.zip"))         # or a folder: export.save(Path("out"))

`manifest.json` records the format, the label source, the query, how many clusters were
exported (`corrected`: how many of them with a person's label), how many were skipped and why
(a detection a person rejected is), and the classes in id order.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from itertools import chain
from pathlib import Path

from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types.curation import rejected

from .archive import Archive, ChunkSink, FolderArchive, ZipArchive, add_json
from .coco import Coco
from .imagefolder import ImageFolder
from .jsonl import Jsonl
from .labels import label_of
from .model import ExportQuery
from .selection import Selection
from .writer import Item, Summary, Writer
from .yolo import Yolo

WRITERS: dict[str, type[Writer]] = {"coco": Coco, "yolo": Yolo, "imagefolder": ImageFolder,
                                    "jsonl": Jsonl}
REJECTED = "rejected by a person"
PIXELS = {"imagefolder": "crops", "jsonl": None}  # coco and yolo: the query's `images`


class NothingExported(ValueError):
    """No selected cluster made it into the export (the message says why)."""


class Export:
    def __init__(self, store: MemoryStore, query: ExportQuery, settings: Settings | None = None):
        self.query = query
        self.selection = Selection(store, query, (settings or Settings()).query_timeout_ms,
                                   PIXELS.get(query.format, query.images))
        self.total = self.selection.count()
        self.summary = Summary()

    def write(self, archive: Archive) -> Iterator[int]:
        """Write the export into `archive`, yielding how many clusters each step handled."""
        writer = WRITERS[self.query.format](archive, self.query, self.summary)
        limit = self.query.limit  # of clusters exported, not selected: skipped ones are not
        for group in self.selection.groups():
            items = []
            for cluster in group.clusters:
                if limit is not None and len(items) == limit - self.summary.exported:
                    break
                if rejected(cluster.annotations):
                    writer.skip(REJECTED)
                elif (label := label_of(cluster, self.query.label, group.object_names)) is None:
                    writer.skip(f"no {self.query.label} label")
                else:
                    items.append(Item(group.scene, cluster, label))
            writer.add(items)
            yield len(group.clusters)
            if limit is not None and self.summary.exported == limit:
                break
        writer.finish()
        add_json(archive, "manifest.json", self._manifest(writer))

    def zip_stream(self) -> Iterator[bytes]:
        """The export as a zip, chunk by chunk, as it is written."""
        sink = ChunkSink()
        archive = ZipArchive(sink)
        for _ in self.write(archive):
            yield from sink.drain()
        archive.close()
        yield from sink.drain()

    def started(self) -> Iterator[bytes]:
        """The zip stream, run here up to its first exported cluster, so that an export with
        nothing in it raises NothingExported before a byte is sent (skipped clusters write
        nothing, so what is held back is at most one scene's entries)."""
        stream = self.zip_stream()
        head = []
        for chunk in stream:
            head.append(chunk)
            if self.summary.exported:
                return chain(head, stream)
        raise NothingExported(self.summary.why_empty())

    def save(self, path: Path, progress: Callable[[int], None] = lambda done: None) -> Summary:
        """Write the export to a zip file (a path ending in .zip) or a new folder, never over
        one. It is written beside `path` under a hidden name and given `path` once whole: an
        export that fails, is stopped (even by SIGKILL) or holds nothing (NothingExported)
        leaves nothing at `path`, so a script that finds the file finds an export."""
        zipped = path.suffix.lower() == ".zip"
        _refuse_taken(path, zipped)
        partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
        try:
            if zipped:
                with partial.open("xb") as file:
                    self._save(ZipArchive(file), progress)
            else:
                self._save(FolderArchive(partial), progress)
            if not self.summary.exported:
                raise NothingExported(self.summary.why_empty())
            _publish(partial, path, zipped)
        except BaseException:
            _remove(partial)
            raise
        return self.summary

    def _save(self, archive, progress: Callable[[int], None]) -> None:
        try:
            for done in self.write(archive):
                progress(done)
        except BaseException:
            archive.abandon()
            raise
        archive.close()

    def _manifest(self, writer: Writer) -> dict:
        return {
            "format": self.query.format,
            "label": self.query.label,
            "images": self.query.images,
            "query": self.query.model_dump(mode="json", exclude_defaults=True),
            "exported": self.summary.exported,
            "corrected": self.summary.corrected,
            "skipped": dict(sorted(self.summary.skipped.items())),
            "classes": list(writer.classes),
        }


def _refuse_taken(path: Path, zipped: bool) -> None:
    if not path.exists():
        return
    if zipped:
        raise FileExistsError(f"{path} exists: an export never writes over it; choose a new "
                              "path")
    if not path.is_dir() or any(path.iterdir()):
        raise FileExistsError(f"{path} exists and is not an empty folder: choose a new path "
                              "(or one ending in .zip for a zip file)")


def _publish(partial: Path, path: Path, zipped: bool) -> None:
    """The whole export under its name, unless something took the name meanwhile."""
    if not zipped:
        _refuse_taken(path, zipped)
        os.replace(partial, path)  # (onto an empty folder, or a new name)
        return
    try:
        os.link(partial, path)  # FileExistsError when taken: never over a file
    except FileExistsError:
        _refuse_taken(path, zipped)
        raise
    except OSError:  # a file system without hard links
        _refuse_taken(path, zipped)
        os.replace(partial, path)
        return
    partial.unlink()


def _remove(path: Path) -> None:
    """The zip file or folder an export was writing."""
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
