"""A generated kitchen week: the demo's data and the ground truth later features are tested on.

Four supporting surfaces of a kitchen, twenty household objects of sixteen kinds (three
identical white cups, two identical plates, a second Pringles can bought when the first is
finished) and a week of routines: breakfast, lunch, snack and dinner are set out and cleared
away, dishes go to the sink and back, milk and juice come out of the fridge and go back, the
water bottle leaves for a few days, an apple is bought and eaten, things are nudged and turned
round. Between these episodes a PR2 looks at each surface in turn (6-10 rounds a day), and every
object on the surface in view becomes a cluster annotated as RoboSherlock's annotators would:
image ROI with crop, mask and pHash, location, classification, shape, colours, OCR text
(sometimes misread), logo, product.

Everything is a function of the seed: the same seed gives bit-identical scenes. `Truth` says
which object every cluster is, every action with its time, and what was where at any time, so
identity resolution (stay / move / newview / appear / hidden / disappear) and the where-is,
where-was, what-was-there and what-changed queries can be checked against it.
"""

from __future__ import annotations

import bisect
import functools
import math
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Literal

import cv2
import imagehash
import numpy as np
from PIL import Image as PILImage

from percept_memory.ingest.synthetic import KINECT
from percept_memory.memory.types import (
    Classification,
    Cluster,
    ColorHistogram,
    Image,
    ImageROI,
    Location,
    LogLine,
    Logo,
    Product,
    Scene,
    SemanticColor,
    Shape,
    Text,
    Transform,
    timestamp_from_datetime,
)

START = datetime(2024, 3, 4, tzinfo=UTC)
"""Monday 00:00 UTC of the first day. Clock times in the schedule are UTC ("8 am" is 08:00)."""
ROBOT = "pr2"
MAP = "kitchen-week"  # a kitchen of its own: never one object with the real data's
CROP = 64
CAMERA_HEIGHT = 1.55
SECOND = 1_000_000_000

ActionKind = Literal["put", "move", "take", "bring_back", "turn"]
Event = Literal["appear", "stay", "move", "newview"]
Face = Literal["front", "back"]
Vec3 = tuple[float, float, float]


# --- the world ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Region:
    """A supporting surface: its extent in the map frame and where the robot's head camera is
    when it looks at it (chosen so the whole surface is in view and no other surface is)."""

    name: str
    x: tuple[float, float]
    y: tuple[float, float]
    z: float
    standpoint: Vec3

    @property
    def center(self) -> Vec3:
        return ((self.x[0] + self.x[1]) / 2, (self.y[0] + self.y[1]) / 2, self.z)


REGIONS: dict[str, Region] = {r.name: r for r in (
    Region("counter_top_sink", (0.05, 0.65), (1.4, 2.6), 0.90, (2.0, 2.0, CAMERA_HEIGHT)),
    Region("counter_top_island", (2.6, 3.4), (1.4, 2.6), 0.90, (1.25, 2.0, CAMERA_HEIGHT)),
    Region("table", (1.3, 2.5), (4.2, 5.0), 0.74, (1.9, 2.95, CAMERA_HEIGHT)),
    Region("shelf", (1.2, 2.6), (0.05, 0.4), 1.20, (1.9, 1.85, CAMERA_HEIGHT)),
)}
"""The kitchen, in metres in the map frame: the sink counter along the west wall, the island
across the aisle from it, the dining table to the north and a wall shelf to the south."""


@dataclass(frozen=True)
class Item:
    """A kind of household object in the catalogue, with everything that makes it look the
    same every time: how it is drawn (`look`, colours by PALETTE name, printed lines) and what
    recognisers say about it."""

    key: str
    name: str
    class_name: str
    shape: str  # what a primitive-shape annotator calls it
    look: str  # how it is drawn: box, carton, can, bottle, squeeze, jar, bar, block, cup, ...
    size: Vec3  # width, depth, height in metres
    colours: tuple[str, str, str]  # body, accent, ink
    front: tuple[str, ...] = ()  # printed lines OCR can read on the front
    back: tuple[str, ...] | None = None  # the back's lines; None: the same from every side
    brand: str | None = None
    properties: Mapping[str, str | bool | int | float] = field(default_factory=dict)
    home: str | None = None  # where it is kept; None: out of view (the fridge)
    count: int = 1  # visually identical instances
    confused_with: str | None = None  # the class a classifier sometimes takes it for

    @property
    def radius(self) -> float:
        """How far other objects stay from its centre: its footprint's circumradius."""
        if self.shape in ("cylinder", "round", "flat"):
            return max(self.size[0], self.size[1]) / 2
        return math.hypot(self.size[0], self.size[1]) / 2


NUTRITION = ("Nutrition", "per 100g")
CATALOGUE: dict[str, Item] = {i.key: i for i in (
    Item("corn_flakes", "Kellogg's Corn Flakes", "cereal", "box", "box", (0.19, 0.07, 0.28),
         ("yellow", "green", "red"), ("Kellogg's", "Corn Flakes"), NUTRITION, "Kellogg's",
         {"category": "breakfast cereal", "perishable": False, "weight_g": 375}, "shelf",
         confused_with="tea"),
    Item("ketchup", "Heinz Tomato Ketchup", "ketchup", "cylinder", "squeeze", (0.07, 0.05, 0.2),
         ("red", "white", "black"), ("HEINZ", "Ketchup"), ("Tomato", "Ketchup"), "Heinz",
         {"category": "condiment", "perishable": False, "volume_ml": 500}, "shelf",
         confused_with="dish soap"),
    Item("pringles", "Pringles Original", "chips", "cylinder", "can", (0.075, 0.075, 0.23),
         ("red", "white", "white"), ("Pringles", "Original"), NUTRITION, "Pringles",
         {"category": "snack", "perishable": False, "weight_g": 165}, "shelf", count=2,
         confused_with="water"),
    Item("milk", "Weihenstephan Frische Milch", "milk", "box", "carton", (0.07, 0.07, 0.2),
         ("white", "blue", "blue"), ("Frische", "Milch"), ("Weihenstephan",), "Weihenstephan",
         {"category": "dairy", "perishable": True, "volume_ml": 1000, "fat_percent": 3.5}, None,
         confused_with="juice"),
    Item("juice", "Hohes C Orange", "juice", "box", "box", (0.07, 0.07, 0.2),
         ("orange", "green", "white"), ("Hohes C", "Orange"), NUTRITION, "Hohes C",
         {"category": "beverage", "perishable": True, "volume_ml": 1000}, None,
         confused_with="milk"),
    Item("tea", "Lipton Yellow Label Tea", "tea", "box", "box", (0.14, 0.07, 0.08),
         ("yellow", "red", "black"), ("Lipton", "Yellow Label"), ("25 tea bags",), "Lipton",
         {"category": "tea", "perishable": False, "bags": 25}, "shelf", confused_with="cereal"),
    Item("nutella", "Nutella", "spread", "cylinder", "jar", (0.09, 0.09, 0.13),
         ("white", "brown", "red"), ("nutella",), NUTRITION, "Ferrero",
         {"category": "spread", "perishable": False, "weight_g": 450}, "shelf"),
    Item("milka", "Milka Alpenmilch", "chocolate", "box", "bar", (0.17, 0.02, 0.08),
         ("purple", "white", "white"), ("Milka", "Alpenmilch"), NUTRITION, "Milka",
         {"category": "sweets", "perishable": False, "weight_g": 100}, "shelf"),
    Item("fairy", "Fairy Original", "dish soap", "cylinder", "bottle", (0.08, 0.05, 0.22),
         ("green", "white", "blue"), ("Fairy",), ("Original", "450ml"), "Fairy",
         {"category": "household", "perishable": False, "volume_ml": 450}, "counter_top_sink",
         confused_with="ketchup"),
    Item("water", "Gerolsteiner Mineralwasser", "water", "cylinder", "bottle",
         (0.08, 0.08, 0.3), ("blue", "white", "white"), ("Gerolsteiner",), ("Sprudel",),
         "Gerolsteiner", {"category": "beverage", "perishable": False, "volume_ml": 1000},
         "counter_top_island", confused_with="chips"),
    Item("sponge", "sponge", "sponge", "box", "block", (0.09, 0.06, 0.04),
         ("yellow", "green", "green"), home="counter_top_sink"),
    Item("apple", "apple", "apple", "round", "fruit", (0.08, 0.08, 0.08),
         ("red", "green", "brown"), properties={"category": "fruit", "perishable": True},
         home="counter_top_island", confused_with="bowl"),
    Item("mug", "blue mug", "mug", "cylinder", "mug", (0.12, 0.08, 0.1),
         ("blue", "blue", "white"), ("Bremen",), (), home="counter_top_island",
         confused_with="cup"),
    Item("cup", "white cup", "cup", "cylinder", "cup", (0.08, 0.08, 0.09),
         ("white", "grey", "grey"), home="counter_top_island", count=3, confused_with="mug"),
    Item("plate", "white plate", "plate", "flat", "plate", (0.24, 0.24, 0.03),
         ("white", "grey", "grey"), home="counter_top_island", count=2, confused_with="bowl"),
    Item("bowl", "blue bowl", "bowl", "round", "bowl", (0.16, 0.16, 0.07),
         ("blue", "white", "white"), home="counter_top_island", confused_with="plate"),
)}
"""The household objects, by catalogue key. An object id is the key and an instance number:
`cup#2`."""

CLASSES = sorted({item.class_name for item in CATALOGUE.values()})
DISHES = ("cup", "plate", "bowl", "mug")


def object_ids() -> list[str]:
    """Every object of the catalogue: `key#n` for each of its instances."""
    return [f"{key}#{n}" for key, item in CATALOGUE.items() for n in range(1, item.count + 1)]


def item_of(object_id: str) -> Item:
    return CATALOGUE[object_id.partition("#")[0]]


# --- appearance -----------------------------------------------------------------------------

PALETTE = {  # BGR
    "white": (232, 232, 228), "grey": (150, 150, 150), "black": (35, 35, 35),
    "red": (40, 40, 200), "orange": (20, 120, 245), "yellow": (40, 210, 245),
    "green": (50, 150, 40), "blue": (170, 90, 20), "purple": (190, 120, 150),
    "brown": (30, 55, 100),
}
BACKGROUND = (105, 115, 120)  # the worktop around the object
CANVAS = 96  # objects are drawn this large, then cut out and scaled to CROP like an ROI
ROUND_LOOKS = ("can", "jar", "bottle", "squeeze", "cup", "mug", "fruit", "bowl")


def _fit_text(image: np.ndarray, lines: tuple[str, ...], box: tuple[int, int, int, int],
              colour: tuple[int, int, int]) -> None:
    """Print `lines` centred in `box` (x, y, w, h), as large as fits."""
    if not lines:
        return
    x, y, w, h = box
    font = cv2.FONT_HERSHEY_SIMPLEX
    widest = max(cv2.getTextSize(line, font, 1.0, 1)[0][0] for line in lines)
    scale = min(0.8, (w - 2) / widest, (h / len(lines) - 2) / 22)
    step = h / len(lines)
    for i, line in enumerate(lines):
        (tw, th), _ = cv2.getTextSize(line, font, scale, 1)
        org = (x + (w - tw) // 2, int(y + step * i + (step + th) / 2))
        cv2.putText(image, line, org, font, scale, colour, 1, cv2.LINE_AA)


def _silhouette(item: Item, face: Face) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The object's mask on the canvas and the box of its printable body."""
    mask = np.zeros((CANVAS, CANVAS), np.uint8)
    width, _, height = item.size
    if item.look in ("plate", "bowl"):
        height = width * 0.6  # seen from above at an angle
    scale = 72 / max(width, height)
    w, h = max(12, round(width * scale)), max(12, round(height * scale))
    x, y = (CANVAS - w) // 2, (CANVAS - h) // 2
    look = item.look
    if look in ("box", "bar", "block"):
        cv2.rectangle(mask, (x, y), (x + w - 1, y + h - 1), 255, -1)
        return mask, (x, y, w, h)
    if look == "carton":  # gable top
        gable = w // 2
        cv2.rectangle(mask, (x, y + gable), (x + w - 1, y + h - 1), 255, -1)
        cv2.fillConvexPoly(mask, np.array([(x, y + gable), (x + w // 2, y + 3),
                                           (x + w - 1, y + gable)], np.int32), 255)
        cv2.rectangle(mask, (x + w // 2 - 1, y), (x + w // 2 + 1, y + 4), 255, -1)
        return mask, (x, y + gable, w, h - gable)
    if look == "cup":  # a coffee cup: the handle on the right
        w -= w // 5
        cv2.ellipse(mask, (x + w, y + h * 2 // 5), (w // 5, h // 4), 0, -90, 90, 255, 4)
    if look in ("can", "jar", "cup"):
        cap = max(4, w // 5)
        cv2.rectangle(mask, (x, y + cap // 2), (x + w - 1, y + h - 1 - cap // 2), 255, -1)
        for cy in (y + cap // 2, y + h - 1 - cap // 2):
            cv2.ellipse(mask, (x + w // 2, cy), (w // 2, cap // 2), 0, 0, 360, 255, -1)
        return mask, (x, y + cap, w, h - 2 * cap)
    if look == "bottle":
        neck, shoulder = w // 3, y + h * 2 // 5
        cv2.rectangle(mask, (x, shoulder), (x + w - 1, y + h - 1), 255, -1)
        cv2.rectangle(mask, (x + w // 2 - neck // 2, y), (x + w // 2 + neck // 2, shoulder),
                      255, -1)
        cv2.ellipse(mask, (x + w // 2, shoulder), (w // 2, w // 4), 0, 180, 360, 255, -1)
        return mask, (x, shoulder + w // 4, w, y + h - shoulder - w // 4)
    if look == "squeeze":  # standing on its cap
        cap = h // 6
        cv2.rectangle(mask, (x + w // 4, y + h - cap), (x + w * 3 // 4, y + h - 1), 255, -1)
        cv2.ellipse(mask, (x + w // 2, y + w // 2), (w // 2, w // 2), 0, 180, 360, 255, -1)
        cv2.rectangle(mask, (x, y + w // 2), (x + w - 1, y + h - cap - w // 3), 255, -1)
        cv2.ellipse(mask, (x + w // 2, y + h - cap - w // 3), (w // 2, w // 3), 0, 0, 180,
                    255, -1)
        return mask, (x, y + w // 2, w, h - cap - w // 2 - w // 3)
    if look == "mug":  # the handle is on the right of the printed side
        body = w * 3 // 4
        bx = x if face == "front" else x + w - body
        cv2.circle(mask, (bx + body if face == "front" else bx, y + h // 2), h // 4, 255, 4)
        cv2.rectangle(mask, (bx, y), (bx + body - 1, y + h - 1), 255, -1)
        return mask, (bx, y, body, h)
    if look == "plate":
        cv2.ellipse(mask, (x + w // 2, y + h // 2), (w // 2, h // 2), 0, 0, 360, 255, -1)
        return mask, (x, y, w, h)
    if look == "bowl":
        cv2.ellipse(mask, (x + w // 2, y + h // 3), (w // 2, h // 3), 0, 0, 360, 255, -1)
        cv2.ellipse(mask, (x + w // 2, y + h // 3), (w // 2, h * 2 // 3), 0, 0, 180, 255, -1)
        return mask, (x, y, w, h)
    cv2.circle(mask, (x + w // 2, y + h // 2 + 3), min(w, h) // 2 - 3, 255, -1)  # fruit
    cv2.line(mask, (x + w // 2, y + 6), (x + w // 2 + 3, y), 255, 3)
    return mask, (x, y, w, h)


def _decorate(image: np.ndarray, item: Item, face: Face, box: tuple[int, int, int, int]) -> None:
    """Print and paint the object's surface inside its body box."""
    x, y, w, h = box
    _, accent, ink = (PALETTE[c] for c in item.colours)
    look = item.look
    lines = item.front if face == "front" else item.back or ()
    if look in ("cup", "bowl"):  # the inside, seen over the rim
        rim = h // 3 if look == "bowl" else max(4, w // 5) // 2
        cv2.ellipse(image, (x + w // 2, y + rim), (w // 2 - 3, max(1, rim - 2)), 0, 0, 360,
                    accent, -1, cv2.LINE_AA)
    elif look == "plate":  # its well, and the lamp reflected off the glaze
        cv2.ellipse(image, (x + w // 2, y + h // 2), (w // 3, h // 3), 0, 0, 360, accent, 2,
                    cv2.LINE_AA)
        cv2.ellipse(image, (x + w // 3, y + h // 3), (w // 8, h // 10), -20, 0, 360,
                    (255, 255, 255), -1, cv2.LINE_AA)
    elif look == "block":  # a scouring pad on a sponge with pores
        image[y : y + h // 3, x : x + w] = accent
        pores = np.random.default_rng(zlib.crc32(item.key.encode()))
        for _ in range(12):
            cv2.circle(image, (x + int(pores.integers(3, w - 3)),
                               y + h // 3 + int(pores.integers(3, h * 2 // 3 - 3))),
                       int(pores.integers(1, 4)), PALETTE["orange"], -1)
    elif look == "fruit":
        cv2.ellipse(image, (x + w // 2 + 9, y + 5), (8, 3), -30, 0, 360, accent, -1)
    elif look == "mug":
        _fit_text(image, lines, (x, y + h // 4, w, h // 3), ink)
    elif face == "front":
        layout = np.random.default_rng(zlib.crc32(item.key.encode()))
        top = y + round(h * layout.uniform(0.45, 0.75))
        image[top : top + round(h * layout.uniform(0.1, 0.22)), x : x + w] = accent
        centre = (x + round(w * layout.uniform(0.25, 0.75)),
                  y + round(h * layout.uniform(0.3, 0.85)))
        cv2.circle(image, centre, max(4, round(min(w, h) * layout.uniform(0.15, 0.3))),
                   accent if layout.random() < 0.5 else ink, -1, cv2.LINE_AA)
        _fit_text(image, lines, (x, y + h // 12, w, h * 2 // 5), ink)
    else:  # the back: nutrition panel and barcode
        left = zlib.crc32(item.key.encode()) % 2 == 0
        px, pw = x + (w // 10 if left else w // 2), w * 2 // 5
        image[y + h // 5 : y + h * 9 // 10, px : px + pw] = PALETTE["white"]
        for row in range(y + h // 4, y + h * 9 // 10 - 3, 4):
            image[row, px + 3 : px + pw - 3] = PALETTE["black"]
        bx, by = x + (w * 11 // 20 if left else w // 10), y + h * 3 // 5
        for column in range(bx, bx + w * 7 // 20, 3):
            image[by : by + h // 5, column : column + 2] = PALETTE["black"]
        _fit_text(image, lines, (x, y + 2, w, h // 6), ink)


def render(item: Item, face: Face = "front") -> tuple[np.ndarray, np.ndarray]:
    """The object as the camera sees it (BGR canvas) and its mask, drawn the same way every
    time: silhouette, print, light from the upper left (round things get a highlight) and a
    shadow on the worktop. Products wear packaging graphics laid out by their key, so each has
    its own pattern, as real ones do."""
    mask, box = _silhouette(item, face)
    image = np.empty((CANVAS, CANVAS, 3), np.uint8)
    image[:] = BACKGROUND
    image[mask > 0] = PALETTE[item.colours[0]]
    _decorate(image, item, face, box)
    ys, xs = np.nonzero(mask)
    u = (np.arange(CANVAS) - xs.min()) / max(1, xs.max() - xs.min())
    v = (np.arange(CANVAS) - ys.min()) / max(1, ys.max() - ys.min())
    light = 1.15 - 0.25 * u[None, :] - 0.12 * v[:, None]
    if item.look in ROUND_LOOKS:
        light = light * (0.85 + 0.3 * np.exp(-(((u - 0.3) / 0.12) ** 2)))[None, :]
    shadow = cv2.GaussianBlur(np.roll(mask, (3, 5), (0, 1)), (0, 0), 2.0) / 255.0
    shade = np.where(mask > 0, light, 1.0 - 0.45 * shadow)
    lit = np.clip(image * shade[..., None], 0, 255).astype(np.uint8)
    return lit, mask


@dataclass(frozen=True)
class _Look:
    """A rendered side of an object, and the square window an ROI around it would cut."""

    picture: np.ndarray
    mask: np.ndarray
    window: tuple[int, int, int]  # x, y, side


@functools.cache
def _look(key: str, face: Face) -> _Look:
    picture, mask = render(CATALOGUE[key], face)
    ys, xs = np.nonzero(mask)
    side = max(xs.max() - xs.min(), ys.max() - ys.min()) + 1 + 8
    x = (xs.min() + xs.max() + 1 - side) // 2
    y = (ys.min() + ys.max() + 1 - side) // 2
    return _Look(picture, mask, (int(x), int(y), int(side)))


def crop(key: str, face: Face, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One observation's crop and mask (CROP x CROP): the object's square ROI, off by up to a
    pixel as segmentation is, scaled, with the exposure and sensor noise of this frame. (Two
    pixel offsets move the same object's pHash by up to ~20 bits, as far as other objects.)"""
    look = _look(key, face)
    dx, dy = (int(v) for v in rng.integers(-1, 2, 2))
    x, y, side = look.window
    window = np.s_[y + dy : y + dy + side, x + dx : x + dx + side]
    image = cv2.resize(look.picture[window], (CROP, CROP), interpolation=cv2.INTER_AREA)
    mask = cv2.resize(look.mask[window], (CROP, CROP), interpolation=cv2.INTER_NEAREST)
    noisy = image * rng.normal(1.0, 0.04) + rng.normal(0.0, 4.0) + rng.normal(0.0, 2.0,
                                                                               image.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8), mask


def phash(image: np.ndarray) -> str:
    """64-bit perceptual hash of a BGR image, as 16 hex digits."""
    return str(imagehash.phash(PILImage.fromarray(np.ascontiguousarray(image[..., ::-1]))))


COLOUR_NAMES = ("red", "orange", "yellow", "green", "blue", "purple", "black", "white", "grey",
                "brown")
HUE_BOUNDS = np.array([8, 20, 35, 85, 130, 165])  # OpenCV hue (0-180) where each name ends


def colour_names(image: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Share of the masked pixels of each named colour (those over 5 %), as a colour namer
    working on hue, saturation and value would give them."""
    hue, sat, val = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)[mask > 0].T.astype(int)
    names = np.searchsorted(HUE_BOUNDS, hue, side="right") % 6  # past purple is red again
    names[(names == 1) & (val < 140)] = 9
    names[sat < 50] = np.where(val[sat < 50] > 170, 7, 8)
    names[val < 60] = 6
    shares = np.bincount(names, minlength=len(COLOUR_NAMES)) / len(names)
    kept = {COLOUR_NAMES[i]: float(share) for i, share in enumerate(shares) if share >= 0.05}
    total = sum(kept.values())
    return {name: round(share / total, 3) for name, share in sorted(kept.items())}


def colour_histogram(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """16 x 16 hue-saturation histogram of the masked pixels, summing to 1."""
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    histogram = cv2.calcHist([hsv], [0, 1], mask, [16, 16], [0, 180, 0, 256])
    return (histogram / max(1.0, float(histogram.sum()))).astype(np.float32)


# --- the truth ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Action:
    """Something a person did: `put` (an object is seen in the kitchen for the first time),
    `move` (to another surface, or another place on the same one), `take` (off every surface:
    into the fridge, the bin, another room), `bring_back` (a taken object returns), `turn`
    (rotated in place: the camera sees its other side)."""

    time: int
    object: str
    kind: ActionKind
    from_region: str | None
    to_region: str | None
    position: Vec3 | None  # where it stands afterwards (its centre), None once taken
    face: Face = "front"  # the side facing the robot's standpoint afterwards


@dataclass(frozen=True)
class Observation:
    """Cluster `cluster` of scene `scene` is `object`. `event` is what happened to the object
    since the robot last saw it: appear (never seen before), stay (same place, same side),
    newview (same place, turned), move (anywhere else, including after being taken away and
    brought back)."""

    scene: int
    cluster: int
    object: str
    position: Vec3  # true centre, before measurement noise
    face: Face
    event: Event


@dataclass(frozen=True)
class SceneTruth:
    """What scene `index` saw: the objects on its region in cluster order, and `gone`: those
    the robot last saw on this region that are no longer there (a belief state should now say
    they disappeared; every object elsewhere is merely out of view, hidden)."""

    index: int
    round: int
    time: int
    region: str
    objects: tuple[str, ...]
    gone: tuple[str, ...]


@dataclass
class Truth:
    """The ground truth of a generated week, with the questions tests and demos ask of it."""

    actions: list[Action]
    scenes: list[SceneTruth]
    observations: list[Observation]
    _timelines: dict[str, tuple[list[int], list[Action]]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._timelines = {}
        for action in sorted(self.actions, key=lambda a: a.time):
            times, actions = self._timelines.setdefault(action.object, ([], []))
            times.append(action.time)
            actions.append(action)

    @property
    def objects(self) -> list[str]:
        """Every object that was in the kitchen at some time."""
        return sorted(self._timelines)

    def object_at(self, scene: int, cluster: int) -> str:
        return self.scenes[scene].objects[cluster]

    def _last(self, object_id: str, t: int) -> Action | None:
        times, actions = self._timelines.get(object_id, ([], []))
        i = bisect.bisect_right(times, t)
        return actions[i - 1] if i else None

    def where_at(self, object_id: str, t: int) -> str | None:
        """The region the object is on at time `t` (ns), None when it is on none."""
        last = self._last(object_id, t)
        return last.to_region if last else None

    def position_at(self, object_id: str, t: int) -> Vec3 | None:
        last = self._last(object_id, t)
        return last.position if last else None

    def objects_on(self, region: str, t: int) -> list[str]:
        return [o for o in self.objects if self.where_at(o, t) == region]

    def actions_between(self, t0: int, t1: int, region: str | None = None) -> list[Action]:
        """Actions after `t0` up to `t1` (what changed), those touching `region` if given."""
        return [a for a in self.actions if t0 < a.time <= t1
                and (region is None or region in (a.from_region, a.to_region))]

    def observations_of(self, object_id: str) -> list[Observation]:
        return [o for o in self.observations if o.object == object_id]


@dataclass
class KitchenWeek:
    """The scenes in time order (ids unassigned, ready to ingest) and their ground truth."""

    scenes: list[Scene]
    truth: Truth


# --- the week -------------------------------------------------------------------------------


class _Kitchen:
    """The true state while the week is simulated, and the actions that change it."""

    def __init__(self, rng: np.random.Generator, clock: int):
        self.rng = rng
        self.clock = clock
        self.on_region: dict[str, tuple[str, Vec3, Face]] = {}
        self.away = {o: "shop" for o in object_ids()}  # shop, fridge, office, bin, ...
        self.away.update({"milk#1": "fridge", "juice#1": "fridge"})
        self.seen: set[str] = set()  # objects that have been on a surface
        self.actions: list[Action] = []

    def on(self, region: str, key: str | None = None) -> list[str]:
        return [o for o, (r, _, _) in sorted(self.on_region.items())
                if r == region and (key is None or o.startswith(key + "#"))]

    def available(self, object_id: str) -> bool:
        return object_id in self.on_region or self.away.get(object_id) == "fridge"

    def _spot(self, object_id: str, region: str) -> Vec3:
        """A free place for the object on the region, away from its current place."""
        area, item = REGIONS[region], item_of(object_id)
        here = self.on_region.get(object_id)
        for _ in range(2000):
            x = float(self.rng.uniform(area.x[0] + item.radius, area.x[1] - item.radius))
            y = float(self.rng.uniform(area.y[0] + item.radius, area.y[1] - item.radius))
            if here and here[0] == region and math.dist((x, y), here[1][:2]) < 0.1:
                continue
            if all(math.dist((x, y), p[:2]) >= item.radius + item_of(o).radius + 0.01
                   for o, (r, p, _) in self.on_region.items() if r == region and o != object_id):
                return (round(x, 4), round(y, 4), round(area.z + item.size[2] / 2, 4))
        raise RuntimeError(f"no room for {object_id} on {region}")

    def _record(self, object_id: str, kind: ActionKind, to: str | None, position: Vec3 | None,
                face: Face) -> None:
        here = self.on_region.get(object_id)
        self.actions.append(Action(self.clock, object_id, kind, here[0] if here else None, to,
                                   position, face))
        if to is None:
            self.on_region.pop(object_id)
        else:
            self.on_region[object_id] = (to, position, face)
        self.clock += int(self.rng.integers(15, 90)) * SECOND + int(self.rng.integers(SECOND))

    def place(self, object_id: str, region: str) -> None:
        """Put the object on the region, labels facing the room most of the time."""
        if object_id in self.on_region:
            kind: ActionKind = "move"
        else:
            kind = "bring_back" if object_id in self.seen else "put"
            self.away.pop(object_id)
            self.seen.add(object_id)
        turnable = item_of(object_id).back is not None
        face: Face = "back" if turnable and self.rng.random() < 0.15 else "front"
        self._record(object_id, kind, region, self._spot(object_id, region), face)

    def fetch(self, object_id: str | None, region: str) -> None:
        """Bring the object to the region if it can be had and is not there already."""
        if object_id and self.available(object_id) and self.where(object_id) != region:
            self.place(object_id, region)

    def take(self, object_id: str, to: str) -> None:
        if object_id in self.on_region:
            self.away[object_id] = to
            self._record(object_id, "take", None, None, "front")

    def turn(self, object_id: str) -> None:
        region, position, face = self.on_region[object_id]
        self._record(object_id, "turn", region, position, "back" if face == "front" else "front")

    def where(self, object_id: str) -> str | None:
        here = self.on_region.get(object_id)
        return here[0] if here else None

    def clean(self, key: str) -> str | None:
        """One of the clean dishes of this kind (they are kept on the island), any of them."""
        dishes = self.on("counter_top_island", key)
        return str(self.rng.choice(dishes)) if dishes else None

    def put_away(self, object_id: str) -> None:
        """Used dishes to the sink, perishables to the fridge, the rest where it belongs."""
        item = item_of(object_id)
        if item.key in DISHES:
            self.place(object_id, "counter_top_sink")
        elif item.home is None:
            self.take(object_id, "fridge")
        elif self.where(object_id) != item.home:
            self.place(object_id, item.home)


def _chance(k: _Kitchen, p: float) -> bool:
    return bool(k.rng.random() < p)


def _breakfast(k: _Kitchen) -> None:
    for object_id, p in (("corn_flakes#1", 0.85), ("milk#1", 0.9), ("juice#1", 0.6),
                         ("nutella#1", 0.35)):
        if _chance(k, p):
            k.fetch(object_id, "table")
    for key, p in (("bowl", 0.85), ("mug", 0.8), ("cup", 0.5), ("plate", 0.3)):
        if _chance(k, p) or key == "plate" and k.where("nutella#1") == "table":
            k.fetch(k.clean(key), "table")


def _meal(k: _Kitchen, plates: int, cups: int) -> None:
    for _ in range(plates):
        k.fetch(k.clean("plate"), "table")
    for _ in range(cups):
        k.fetch(k.clean("cup"), "table")
    for object_id, p in (("ketchup#1", 0.65), ("water#1", 0.6)):
        if _chance(k, p):
            k.fetch(object_id, "table")


def _snack(k: _Kitchen) -> None:
    for pringles in ("pringles#1", "pringles#2"):
        if _chance(k, 0.5):
            k.fetch(pringles, str(k.rng.choice(["table", "counter_top_island"])))
    if _chance(k, 0.4):
        k.fetch("milka#1", "table")
    if _chance(k, 0.45):
        k.fetch("tea#1", "table")
        k.fetch(k.clean("cup"), "table")


def _clear(k: _Kitchen, leave: float = 0.1) -> None:
    """Clear the table; now and then something is left there until later."""
    for object_id in k.on("table"):
        if not _chance(k, leave):
            k.put_away(object_id)


def _wash(k: _Kitchen, p: float = 0.8) -> None:
    for dish in k.on("counter_top_sink"):
        if item_of(dish).key in DISHES and _chance(k, p):
            k.place(dish, "counter_top_island")


def _fidget(k: _Kitchen) -> None:
    """Someone nudges a thing to another place on its surface, or turns one round."""
    present = sorted(k.on_region)
    if present and _chance(k, 0.5):
        nudged = str(k.rng.choice(present))
        k.place(nudged, k.where(nudged))
    turnable = [o for o in present if item_of(o).back is not None]
    if turnable and _chance(k, 0.5):
        k.turn(str(k.rng.choice(turnable)))


def _tidy(k: _Kitchen, p: float) -> None:
    """Put away what was left on the island that is not kept there."""
    for object_id in k.on("counter_top_island"):
        item = item_of(object_id)
        if item.key not in DISHES and item.home != "counter_top_island" and _chance(k, p):
            k.put_away(object_id)


def _wash_up(k: _Kitchen) -> None:
    _wash(k)
    _fidget(k)


def _clear_lunch(k: _Kitchen) -> None:
    _clear(k)
    _fidget(k)


def _clear_snack(k: _Kitchen) -> None:
    _clear(k, leave=0.2)
    _tidy(k, 0.5)
    _fidget(k)


def _night(k: _Kitchen) -> None:
    _clear(k, leave=0.0)
    _tidy(k, 1.0)
    _wash(k, 0.5)
    _fidget(k)


def _shopping(k: _Kitchen) -> None:
    k.place("apple#1", "counter_top_island")
    k.place("milka#1", "shelf")


ROUTINES: dict[str, Callable[[_Kitchen], None]] = {
    "breakfast": _breakfast,
    "clear_breakfast": _clear,
    "wash": _wash_up,
    "lunch": lambda k: _meal(k, plates=int(k.rng.integers(1, 3)), cups=int(k.rng.integers(2))),
    "clear_lunch": _clear_lunch,
    "snack": _snack,
    "clear_snack": _clear_snack,
    "dinner": lambda k: _meal(k, plates=2, cups=int(k.rng.integers(1, 3))),
    "clear_dinner": _clear,
    "night": _night,
}

SPECIALS: dict[tuple[int, str], Callable[[_Kitchen], None]] = {
    (1, "wash"): lambda k: k.take("water#1", "office"),
    (2, "clear_snack"): _shopping,
    (3, "clear_dinner"): lambda k: k.place("water#1", "counter_top_island"),
    (4, "snack"): lambda k: k.take("apple#1", "bin"),
    (5, "clear_dinner"): lambda k: k.take("pringles#1", "bin"),
    (6, "clear_snack"): lambda k: k.place("pringles#2", "shelf"),
}
"""The week's story, by (day, episode): the water bottle goes to the office on Tuesday and
comes back on Thursday, an apple and a chocolate bar are bought on Wednesday, the apple is
eaten on Friday, the Pringles are finished on Saturday and an identical new can is bought on
Sunday."""

DAY: tuple[tuple[str, str, float], ...] = (
    ("06:30", "round", 1.0), ("07:10", "breakfast", 0.95), ("07:50", "round", 1.0),
    ("08:40", "clear_breakfast", 1.0), ("09:30", "round", 0.75), ("10:15", "wash", 0.9),
    ("11:15", "round", 0.7), ("12:10", "lunch", 0.85), ("12:50", "round", 1.0),
    ("13:30", "clear_lunch", 1.0), ("14:30", "round", 0.7), ("15:20", "snack", 0.8),
    ("16:00", "round", 0.8), ("16:45", "clear_snack", 1.0), ("17:45", "round", 0.7),
    ("18:30", "dinner", 0.9), ("19:15", "round", 1.0), ("20:00", "clear_dinner", 1.0),
    ("21:00", "round", 0.8), ("21:45", "night", 1.0),
)
"""A day: (UTC clock time, what happens, how likely it happens that day). A round is the
robot looking at each surface in turn; the rest are the household's routines. Times vary by
up to 8 minutes, so rounds and routines never overlap."""

INITIAL = {
    "shelf": ("corn_flakes#1", "pringles#1", "tea#1", "nutella#1", "ketchup#1"),
    "counter_top_sink": ("fairy#1", "sponge#1"),
    "counter_top_island": ("cup#1", "cup#2", "cup#3", "plate#1", "plate#2", "bowl#1", "mug#1",
                           "water#1"),
}
"""Monday 06:00: where things are when the robot starts (milk and juice are in the fridge)."""
ROUTE = ("counter_top_sink", "counter_top_island", "table", "shelf")


# --- the robot's view -----------------------------------------------------------------------


def _camera(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation of an optical frame (z forward, x right, y down) at `eye` looking at `target`:
    its columns are the camera axes in the map frame."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    return np.column_stack([right, np.cross(forward, right), forward])


def _quaternion(m: np.ndarray) -> tuple[float, float, float, float]:
    """x, y, z, w of a rotation matrix (Shepperd's method: divide by the largest term)."""
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > max(m[0, 0], m[1, 1], m[2, 2]):
        s = 2 * math.sqrt(1 + trace)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2 * math.sqrt(1 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] >= m[2, 2]:
        s = 2 * math.sqrt(1 - m[0, 0] + m[1, 1] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2 * math.sqrt(1 - m[0, 0] - m[1, 1] + m[2, 2])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)
    return tuple(float(v) for v in q)  # type: ignore[return-value]


def project(pose: Transform, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) of map points (N, 3) in the Kinect image, and their depths."""
    matrix = pose.matrix()
    in_camera = (points - matrix[:3, 3]) @ matrix[:3, :3]
    depth = in_camera[:, 2]
    (fx, fy), (cx, cy) = KINECT.focal, KINECT.principal_point
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = np.column_stack([fx * in_camera[:, 0] / depth + cx,
                                  fy * in_camera[:, 1] / depth + cy])
    return pixels, depth


def corners(object_id: str, position: Vec3) -> np.ndarray:
    """The 8 corners of the object's upright bounding box around its centre."""
    item = item_of(object_id)
    r, half = max(item.size[:2]) / 2, item.size[2] / 2
    return np.array([(position[0] + sx * r, position[1] + sy * r, position[2] + sz * half)
                     for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])


def _camera_pose(region: Region, rng: np.random.Generator, stamp: int) -> Transform:
    """The head camera at the region's standpoint, as the robot parked this time."""
    eye = np.array(region.standpoint) + rng.normal(0, (0.03, 0.03, 0.01))
    target = np.array(region.center) + (0, 0, 0.1) + rng.normal(0, 0.02, 3)
    return Transform(translation=tuple(float(v) for v in eye),
                     rotation=_quaternion(_camera(eye, target)), frame="map",
                     child_frame=KINECT.frame, stamp=stamp)


def _box(pose: Transform, object_id: str, position: Vec3) -> tuple[int, int, int, int]:
    pixels, _ = project(pose, corners(object_id, position))
    x0, y0 = np.floor(pixels.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pixels.max(axis=0)).astype(int)
    x0, y0 = max(0, int(x0)), max(0, int(y0))
    x1, y1 = min(KINECT.width, int(x1)), min(KINECT.height, int(y1))
    return x0, y0, x1 - x0, y1 - y0


MISREAD = {"l": "1", "o": "0", "O": "0", "e": "c", "i": "l", "g": "q", "n": "m", "S": "5",
           "C": "G", "a": "o", "h": "b"}


def misread(text: str, rng: np.random.Generator) -> str:
    """OCR's typical slip in one word: a letter lost (Pringles -> Prinles) or mistaken."""
    words = text.split()
    long = [i for i, word in enumerate(words) if len(word) >= 4] or [0]
    i = int(rng.choice(long))
    word = words[i]
    j = int(rng.integers(1, max(2, len(word) - 1)))
    if word[j] in MISREAD and rng.random() < 0.5:
        words[i] = word[:j] + MISREAD[word[j]] + word[j + 1 :]
    else:
        words[i] = word[:j] + word[j + 1 :]
    return " ".join(words)


def _classification(item: Item, rng: np.random.Generator) -> Classification:
    """An SVM's verdict over the catalogue's classes: mostly right and sure; now and then it
    takes the object for its look-alike, with less than even confidence."""
    if item.confused_with and rng.random() < 0.06:
        top = {item.confused_with: float(rng.uniform(0.4, 0.49))}
        top[item.class_name] = float(rng.uniform(0.25, top[item.confused_with] - 0.03))
    else:
        top = {item.class_name: float(rng.uniform(0.55, 0.95))}
    others = [c for c in CLASSES if c not in top]
    rest = (1 - sum(top.values())) * rng.dirichlet(np.full(len(others), 0.3))
    scores = top | dict(zip(others, rest.tolist(), strict=True))
    confidences = {c: round(scores[c], 3) for c in CLASSES}
    best = max(confidences, key=confidences.__getitem__)
    return Classification(source="SVMClassifier", class_name=best,
                          confidence=confidences[best], classifier="SVM", feature="VFH",
                          confidences=confidences)


def _cluster(object_id: str, position: Vec3, face: Face, region: str, box: tuple,
             rng: np.random.Generator) -> tuple[Cluster, dict[str, int]]:
    """The cluster annotators make of one object, and how many of each optional annotation
    (text, logo, product) they found."""
    item = item_of(object_id)
    image, mask = crop(item.key, face, rng)
    measured = tuple(round(float(v), 4) for v in np.array(position) + rng.normal(0, 0.01, 3))
    annotations = [
        Location(source="RegionFilter", region=region, position=measured, relation="on"),
        _classification(item, rng),
        Shape(source="PrimitiveShapeAnnotator", shape=item.shape,
              confidence=round(float(rng.uniform(0.6, 0.95)), 3)),
        SemanticColor(source="ClusterColorHistogramCalculator",
                      ratios=colour_names(image, mask)),
        ColorHistogram(source="ClusterColorHistogramCalculator",
                       histogram=colour_histogram(image, mask)),
    ]
    found = {"text": 0, "logo": 0, "product": 0}
    printed = item.front if face == "front" else item.back
    if printed and rng.random() < 0.85:
        text = " ".join(printed)
        if rng.random() < 0.12:
            text, confidence = misread(text, rng), rng.uniform(0.3, 0.6)
        else:
            confidence = rng.uniform(0.7, 0.97)
        annotations.append(Text(source="OCRAnnotator", text=text,
                                confidence=round(float(confidence), 3)))
        found["text"] = 1
    if item.brand and rng.random() < (0.8 if face == "front" else 0.25):
        annotations.append(Logo(source="LogoDetector", brand=item.brand,
                                confidence=round(float(rng.uniform(0.6, 0.95)), 3)))
        found["logo"] = 1
    if item.brand and rng.random() < (0.75 if face == "front" else 0.35):
        annotations.append(Product(source="ProductRecognizer", name=item.name,
                                   brand=item.brand, properties=dict(item.properties)))
        found["product"] = 1
    roi = ImageROI(box=box, crop=Image(data=image, encoding="bgr8"),
                   mask=Image(data=mask, encoding="mono8"), phash=phash(image))
    return Cluster(hypotheses=[roi], annotations=annotations), found


ANNOTATORS = (  # name, milliseconds per scene, per cluster, what it reports
    ("CollectionReader", 4.0, 0.0, "frame received"),
    ("PlaneAnnotator", 14.0, 0.0, "support plane of {region}"),
    ("PointCloudClusterExtractor", 28.0, 3.0, "{clusters} clusters"),
    ("RegionFilter", 1.0, 0.2, "{clusters} clusters on {region}"),
    ("ClusterColorHistogramCalculator", 0.5, 1.5, "{clusters} colour histograms"),
    ("PrimitiveShapeAnnotator", 1.0, 6.0, "{clusters} shapes"),
    ("SVMClassifier", 2.0, 9.0, "{clusters} classified"),
    ("OCRAnnotator", 5.0, 110.0, "{text} texts read"),
    ("LogoDetector", 3.0, 45.0, "{logo} logos"),
    ("ProductRecognizer", 3.0, 70.0, "{product} products"),
)


def _log(stamp: int, region: str, found: list[dict[str, int]],
         rng: np.random.Generator) -> list[LogLine]:
    """A line per annotator with how long it took, plus OCR's complaints about clusters it
    found no text on."""
    counts = {k: sum(f[k] for f in found) for k in ("text", "logo", "product")}
    lines, clock = [], stamp
    for name, fixed, per_cluster, message in ANNOTATORS:
        duration = (fixed + per_cluster * len(found)) * float(rng.uniform(0.8, 1.3))
        lines.append(LogLine(source=name, time=clock, duration_ms=round(duration, 2),
                             message=message.format(region=region, clusters=len(found),
                                                    **counts)))
        clock += int(duration * 1e6)
    return lines


def _scene(stamp: int, region: str, placed: list[tuple[str, Vec3, Face]],
           rng: np.random.Generator) -> tuple[Scene, list[tuple[str, Vec3, Face]]]:
    """What the robot perceives looking at `region`, and the objects in cluster order: left
    to right in the image."""
    pose = _camera_pose(REGIONS[region], rng, stamp)
    boxes = {o: _box(pose, o, p) for o, p, _ in placed}
    placed = sorted(placed, key=lambda o: (boxes[o[0]][0], o[0]))
    clusters, found = [], []
    for object_id, position, face in placed:
        cluster, counts = _cluster(object_id, position, face, region, boxes[object_id], rng)
        clusters.append(cluster)
        found.append(counts)
    log = _log(stamp, region, found, rng)
    for i, (counts, (object_id, _, face)) in enumerate(zip(found, placed, strict=True)):
        item = item_of(object_id)
        if not counts["text"] and (item.front if face == "front" else item.back):
            log.append(LogLine(source="OCRAnnotator", level="warning",
                               message=f"cluster {i}: no text found"))
    scene = Scene(timestamp=stamp, robot=ROBOT, map=MAP, camera_pose=pose, camera=KINECT,
                  clusters=clusters, log=log)
    return scene, placed


class _Sightings:
    """Where the robot last saw each object, to say what happened to it (the events a
    perfect identity resolution would report)."""

    def __init__(self) -> None:
        self.last: dict[str, tuple[str | None, Vec3, Face]] = {}

    def event(self, object_id: str, region: str, position: Vec3, face: Face) -> Event:
        before = self.last.get(object_id)
        self.last[object_id] = (region, position, face)
        if before is None:
            return "appear"
        if before[:2] == (region, position):
            return "stay" if before[2] == face else "newview"
        return "move"

    def gone(self, region: str, present: set[str]) -> tuple[str, ...]:
        """Objects last seen on the region that are not there now; once reported, the robot
        no longer believes them there."""
        gone = tuple(o for o, (r, _, _) in sorted(self.last.items())
                     if r == region and o not in present)
        for object_id in gone:
            self.last[object_id] = (None, *self.last[object_id][1:])
        return gone


def generate(days: int = 7, seed: int = 0, *, start: datetime = START) -> KitchenWeek:
    """The kitchen week: `days` days from `start`, midnight UTC of the first day (Monday 4
    March 2024 by default). The same seed gives bit-identical scenes; the household's routines
    and the sensor's noise draw from separate streams of it, and a shorter week is the start
    of a longer one."""
    world_rng, sensor_rng = (np.random.default_rng(s)
                             for s in np.random.SeedSequence(seed).spawn(2))
    midnight = timestamp_from_datetime(start)
    kitchen = _Kitchen(world_rng, midnight + 6 * 3600 * SECOND)
    for region, objects in INITIAL.items():
        for object_id in objects:
            kitchen.place(object_id, region)
    scenes: list[Scene] = []
    truths: list[SceneTruth] = []
    observations: list[Observation] = []
    sightings = _Sightings()
    for day in range(days):
        for clock, what, chance in DAY:
            hours, minutes = map(int, clock.split(":"))
            t = (midnight + (day * 86400 + hours * 3600 + minutes * 60) * SECOND
                 + int(world_rng.integers(-480, 481)) * SECOND + int(world_rng.integers(SECOND)))
            happens = world_rng.random() < chance
            if what != "round":
                kitchen.clock = t
                if happens:
                    ROUTINES[what](kitchen)
                if (day, what) in SPECIALS:
                    SPECIALS[day, what](kitchen)
                continue
            if not happens:
                continue
            round_ = truths[-1].round + 1 if truths else 0
            for region in ROUTE:
                placed = [(o, *kitchen.on_region[o][1:]) for o in kitchen.on(region)]
                scene, placed = _scene(t, region, placed, sensor_rng)
                index = len(scenes)
                observations += [Observation(index, i, o, p, f, sightings.event(o, region, p, f))
                                 for i, (o, p, f) in enumerate(placed)]
                present = tuple(o for o, _, _ in placed)
                gone = sightings.gone(region, set(present))
                scenes.append(scene)
                truths.append(SceneTruth(index, round_, t, region, present, gone))
                t += int(world_rng.integers(30, 100)) * SECOND + int(world_rng.integers(SECOND))
    return KitchenWeek(scenes, Truth(kitchen.actions, truths, observations))
