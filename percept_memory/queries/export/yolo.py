"""YOLO (Ultralytics layout): `images/<name>.png`, `labels/<name>.txt` with one line
`class x_center y_center width height` (fractions of the image) per object, and `data.yaml`
naming the classes."""

from __future__ import annotations

import json

from .archive import add_bytes
from .writer import Item, Writer


class Yolo(Writer):
    def add(self, items: list[Item]) -> None:
        for picture in self.pictures(items):
            image = f"images/{picture.stem}.png"
            add_bytes(self.archive, image, picture.png)
            lines = []
            for number, (item, instance) in enumerate(picture.instances):
                x, y, w, h = instance.box
                lines.append(f"{self.class_id(item.label)} {(x + w / 2) / instance.width:.6f} "
                             f"{(y + h / 2) / instance.height:.6f} {w / instance.width:.6f} "
                             f"{h / instance.height:.6f}\n")
                self.exported(item, {"image": image, "line": number + 1})
            add_bytes(self.archive, f"labels/{picture.stem}.txt", "".join(lines).encode())

    def finish(self) -> None:
        names = "".join(f"  {i}: {json.dumps(name, ensure_ascii=False)}\n"
                        for name, i in self.classes.items())  # (YAML reads \ud83d alone)
        add_bytes(self.archive, "data.yaml", (
            "# percept-memory export: train and val are the same images; split them as you "
            f"need\npath: .\ntrain: images\nval: images\nnc: {len(self.classes)}\nnames:"
            + ("\n" + names if names else " {}\n")).encode())
        super().finish()
