"""The percepts both sides of bench/vs_fiftyone.py store: one shape, the same on both sides.

Each percept is what one detected object gives: a 64 px crop (cut from the real kitchen frame
when it is there, so PNG sizes are those of real pixels), a detection (label and box), a
classification (label and confidence), a position x, y, z in a 50 m x 50 m building, the
region of that position (a 5 m grid: 100 regions), a time (one percept every 3 s) and an OCR
text. Only numpy and OpenCV are used here: FiftyOne's side imports this module from its own
environment, without percept-memory.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

KITCHEN = Path(__file__).resolve().parents[2] / "shared/data/robosherlock/samples/kitchen"
CROP = 64
START = 1_700_000_000_000_000_000  # ns
STEP = 3_000_000_000  # one percept every 3 s
HOUR = 3600 * 10**9
SIDE, CELL = 50.0, 5.0  # the building and its regions' grid, metres
LABELS = ["cereal", "juice", "bowl", "plate", "spoon", "glass", "knife", "cup", "mug", "pan",
          "pot", "fork", "jar", "bottle", "can", "box", "sponge", "towel", "apple", "banana"]
BRANDS = ["kelloggs", "pringles", "lipton", "milka", "nutella", "heinz", "barilla", "danone",
          "nestle", "oreo"]
WORDS = ["original", "classic", "light", "organic", "crunchy", "fresh", "family", "extra",
         "natural", "premium", "mild", "spicy", "sweet", "salted", "golden", "whole"]


def kitchen_image() -> np.ndarray:
    found = sorted(KITCHEN.glob("rgb_*.png"))
    if found:
        return cv2.imread(str(found[0]))
    return np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)


def region_of(x: float, y: float) -> str:
    return f"r{int(x // CELL)}_{int(y // CELL)}"


def percepts(count: int, seed: int = 7) -> Iterator[dict]:
    """`count` percepts as plain data, the crop as a BGR array, oldest first."""
    rng = np.random.default_rng(seed)
    image = kitchen_image()
    for i in range(count):
        top, left = int(rng.integers(0, image.shape[0] - CROP)), int(
            rng.integers(0, image.shape[1] - CROP))
        x, y = (round(float(v), 4) for v in rng.uniform(0, SIDE, 2))
        z = round(float(rng.uniform(0, 2)), 4)
        label = LABELS[int(rng.integers(len(LABELS)))]
        box = [round(float(v), 4) for v in (*rng.uniform(0, 0.8, 2), *rng.uniform(0.05, 0.2, 2))]
        yield {"time": START + i * STEP + int(rng.integers(10**9)), "label": label,
               "confidence": round(float(rng.uniform(0.3, 1)), 4), "box": box,
               "x": x, "y": y, "z": z, "region": region_of(x, y),
               "text": f"{BRANDS[int(rng.integers(len(BRANDS)))]} {label} "
                       f"{WORDS[int(rng.integers(len(WORDS)))]}",
               "crop": image[top:top + CROP, left:left + CROP].copy()}


def png(crop: np.ndarray) -> bytes:
    return cv2.imencode(".png", crop)[1].tobytes()


def query_args(rng: np.random.Generator, count: int) -> dict[str, dict]:
    """Random arguments for each query of the set, as plain data (both sides read them)."""
    end = START + count * STEP
    t = int(rng.integers(START, max(START + 1, end - HOUR)))
    day = min(24 * HOUR, end - START)
    centre = [round(float(v), 4) for v in (*rng.uniform(2, SIDE - 2, 2), rng.uniform(0.5, 1.5))]
    half = 0.5
    return {
        "label": {"label": (label := LABELS[int(rng.integers(len(LABELS)))])},
        "label_field": {"label": label},  # ours: as a predicate on the classification's field
        "text": {"word": WORDS[int(rng.integers(len(WORDS)))]},
        "hour": {"after": t, "before": t + HOUR},
        "box": {"low": [c - half for c in centre], "high": [c + half for c in centre]},
        "sphere": {"center": centre, "radius": 0.75},
        "region_time": {"region": region_of(*rng.uniform(0, SIDE, 2)),
                        "after": (a := int(rng.integers(START, max(START + 1, end - day)))),
                        "before": a + day},
        "knn": {"near": centre, "k": 50},
    }
