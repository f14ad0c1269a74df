"""Scene-log folders: scenes in the interchange format v1, with their images as files.

A folder holds `*.json` files (one scene, or a list of scenes) and `*.jsonl` files (one scene
per line), read in name order. Arrays and images are inline (base64) or relative paths to files
in the folder (`.npy` arrays, PNG/JPEG images), which may not point outside it. The JSON Schema
of a scene is `pmem schema` (or GET /api/schema/scene); docs/interchange.md has an example.
"""

from __future__ import annotations

import base64
import json
import logging
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from percept_memory.memory.types import Scene

from .json_input import loads
from .service import IngestError

IMAGES = "images"
SCENE_FILES = (".json", ".jsonl")  # in any case: RECORDING.JSON is one too

log = logging.getLogger(__name__)


def _problem(where: str, message: str) -> IngestError:
    return IngestError([{"item": where, "path": "", "message": message, "type": "json_invalid"}])


def read_scene_log(folder: Path) -> Iterator[tuple[str, Any]]:
    """(where, scene data) for every scene in the folder; `where` is `file` or `file:line`."""
    folder = Path(folder)
    if not folder.is_dir():
        raise _problem(str(folder), "is not a scene-log folder (no such directory)")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in SCENE_FILES)
    nested = [p for p in folder.rglob("*")
              if p.parent != folder and p.suffix.lower() in SCENE_FILES]
    if nested:  # (their relative image paths would be the folder's: each is a log of its own)
        log.warning("not read: %d scene file(s) in subfolders, such as %s: import each "
                    "folder on its own", len(nested), nested[0].relative_to(folder))
    if not files:
        raise _problem(str(folder), "holds no .json or .jsonl scene files")
    for path in files:
        text = _text(path)
        if path.suffix.lower() == ".jsonl":
            for number, line in enumerate(text.splitlines(), start=1):
                if line.strip():
                    yield f"{path.name}:{number}", _parse(line, f"{path.name}:{number}")
        else:
            data = _parse(text, path.name)
            for index, scene in enumerate(data if isinstance(data, list) else [data]):
                yield (f"{path.name}[{index}]" if isinstance(data, list) else path.name), scene


def _text(path: Path) -> str:
    """The UTF-8 text of a scene file; only regular files are read (a FIFO would block)."""
    if not path.is_file():
        raise _problem(path.name, "is not a regular file")
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as error:
        raise _problem(path.name, f"is not UTF-8 text (byte {error.start}); scene files are "
                                  "JSON in UTF-8") from None


def _parse(text: str, where: str) -> Any:
    try:
        return loads(text)
    except ValueError as error:
        raise _problem(where, f"is not valid JSON: {error}") from None


def write_scene_log(scenes: Iterable[Scene], folder: Path, name: str = "scenes.jsonl") -> int:
    """Write scenes as a scene-log folder: one JSON line per scene, images as PNG/JPEG files
    under images/. Returns the number of scenes written."""
    folder = Path(folder)
    (folder / IMAGES).mkdir(parents=True, exist_ok=True)
    count = 0
    with (folder / name).open("w", encoding="utf-8") as out:
        for count, scene in enumerate(scenes, start=1):
            data = scene.model_dump(mode="json", by_alias=True)
            out.write(json.dumps(_images_to_files(data, folder, f"{count:06d}")) + "\n")
    return count


def _images_to_files(value: Any, folder: Path, stem: str, counter: list[int] | None = None):
    """Every inline PNG/JPEG image in `value` written to a file and replaced by its path."""
    counter = counter if counter is not None else [0]
    if isinstance(value, list):
        return [_images_to_files(item, folder, stem, counter) for item in value]
    if not isinstance(value, dict):
        return value
    for kind, suffix in (("png", ".png"), ("jpeg", ".jpg")):
        if kind in value:
            counter[0] += 1
            relative = f"{IMAGES}/{stem}_{counter[0]:03d}{suffix}"
            (folder / relative).write_bytes(base64.b64decode(value[kind]))
            return {**{k: v for k, v in value.items() if k != kind}, "path": relative}
    return {key: _images_to_files(item, folder, stem, counter) for key, item in value.items()}
