"""ImageFolder (torchvision's layout): each cluster's crop as `<label>/<cluster id>.png`."""

from __future__ import annotations

from . import pixels
from .archive import NAME_CHARACTERS, add_bytes, add_json, file_name
from .writer import Item, Writer


class ImageFolder(Writer):
    def __init__(self, *args):
        super().__init__(*args)
        self.folders: dict[str, str] = {}  # label -> folder name

    def add(self, items: list[Item]) -> None:
        for item in items:
            found = pixels.crop_of(item.cluster, item.scene)
            data = None if found is None else pixels.png(found[1])
            if data is None:
                self.skip("no crop and no scene image" if found is None
                          else "the crop is not an 8 or 16-bit image")
                continue
            name = f"{self._folder(item.label.name)}/{item.cluster.id}.png"
            add_bytes(self.archive, name, data)
            self.class_id(item.label)
            self.exported(item, {"file": name})

    def _folder(self, label: str) -> str:
        """A file-system-safe folder name, distinct for distinct labels, case aside (Cup
        and cup are one folder on Windows and macOS)."""
        if label not in self.folders:
            safe = file_name(label)
            taken = {folder.casefold() for folder in self.folders.values()}
            folder, n = safe, 1
            while folder.casefold() in taken:
                n += 1
                folder = f"{safe[:NAME_CHARACTERS - len(str(n)) - 1]}_{n}"
            self.folders[label] = folder
        return self.folders[label]

    def finish(self) -> None:
        add_json(self.archive, "classes.json", self.folders)
        super().finish()
