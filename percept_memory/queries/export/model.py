"""What to export: a cluster filter (the same as every query's) plus the format's options."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BeforeValidator, Field, model_validator

from percept_memory.queries.model import MAX_LIST, ClusterFilter, Name, listed

Format = Literal["coco", "yolo", "imagefolder", "jsonl"]
LabelSource = Literal["classification", "detection", "ground_truth", "object", "text"]
ImageMode = Literal["auto", "scenes", "crops"]
IMAGE_FORMATS = ("coco", "yolo")
MAX_EXPORT = 2**63 - 1  # clusters: as many as MongoDB can count (and islice can stop at)


class ExportQuery(ClusterFilter):
    """The clusters a filter selects, oldest first, as training data in one format."""

    format: Format = Field(description="coco, yolo, imagefolder or jsonl")
    label: LabelSource = Field(
        default="classification",
        description="where labels come from: classification, detection, ground_truth, "
                    "object (the believed object's name) or text (OCR)")
    images: ImageMode | None = Field(
        default=None, description="coco and yolo: auto (default: the scene image where the "
                                  "cluster's scene has one, else its crop), scenes (whole scene "
                                  "images with the clusters' boxes) or crops")
    feature: Annotated[list[Name], BeforeValidator(listed), Field(max_length=MAX_LIST)] = Field(
        default=[], description="jsonl: feature vector names (VFH, Caffe, color_histogram); "
                                "all a cluster has if none given")
    limit: Annotated[int, Field(ge=1, le=MAX_EXPORT)] | None = Field(
        default=None, description="export at most this many clusters: the oldest that have "
                                  "a label from `label`")

    @model_validator(mode="after")
    def _options_fit_the_format(self):
        if self.images is not None and self.format not in IMAGE_FORMATS:
            raise ValueError(f"`images` is an option of coco and yolo, not of {self.format}")
        if self.feature and self.format != "jsonl":
            raise ValueError(f"`feature` is an option of jsonl, not of {self.format}")
        if self.images is None and self.format in IMAGE_FORMATS:
            object.__setattr__(self, "images", "auto")
        return self

    def cluster_filter(self) -> ClusterFilter:
        return ClusterFilter(**{name: getattr(self, name) for name in ClusterFilter.model_fields})
