"""COCO: `annotations.json` (images, annotations with box and mask as uncompressed RLE,
categories) and the images under `images/`. Ids are numbers in export order; every image and
annotation also names the scene and cluster it came from."""

from __future__ import annotations

import json

from . import pixels
from .archive import Spool, add_bytes
from .writer import Item, Writer

INFO = {"description": "percept-memory export", "version": "1.0"}


class Coco(Writer):
    def __init__(self, *args):
        super().__init__(*args)
        self.images, self.annotations = Spool(), Spool()

    def add(self, items: list[Item]) -> None:
        for picture in self.pictures(items):
            self.images.item({"id": self.images.items + 1, "file_name": f"{picture.stem}.png",
                              "width": picture.instances[0][1].width,
                              "height": picture.instances[0][1].height,
                              "scene_id": str(picture.instances[0][0].scene.id)})
            add_bytes(self.archive, f"images/{picture.stem}.png", picture.png)
            for item, instance in picture.instances:
                self._annotate(item, instance, image_id=self.images.items)

    def _annotate(self, item: Item, instance: pixels.Instance, image_id: int) -> None:
        annotation_id = self.annotations.items + 1
        x, y, w, h = instance.box
        if instance.mask is None:
            area, segmentation = w * h, [[x, y, x + w, y, x + w, y + h, x, y + h]]
        else:
            area, segmentation = int(instance.mask.sum()), pixels.rle(instance.mask)
        self.annotations.item({"id": annotation_id, "image_id": image_id,
                               "category_id": self.class_id(item.label) + 1,
                               "bbox": [x, y, w, h], "area": area, "iscrowd": 0,
                               "segmentation": segmentation,
                               "cluster_id": str(item.cluster.id)})
        self.exported(item, {"annotation_id": annotation_id, "image_id": image_id})

    def finish(self) -> None:
        """annotations.json, put together from the spooled lists."""
        categories = [{"id": i + 1, "name": name, "supercategory": ""}
                      for name, i in self.classes.items()]
        head = b'{"info":' + json.dumps(INFO, sort_keys=True).encode() + \
            b',"licenses":[],"images":['
        middle = b'],"annotations":['
        tail = b'],"categories":' + json.dumps(categories).encode() + b"}\n"

        def chunks():
            yield head
            yield from self.images.chunks()
            yield middle
            yield from self.annotations.chunks()
            yield tail

        self.archive.add("annotations.json", chunks(), len(head) + self.images.size +
                         len(middle) + self.annotations.size + len(tail))
        super().finish()
