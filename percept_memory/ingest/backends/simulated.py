"""A simulated Goggles: the thesis' measured timings and mix of answers, for demos and benchmarks.

Latency (thesis table 5.6, 147 requests): drawn from the histogram, uniform within each 100 ms
bin; the lowest bin starts at the measured minimum (504 ms) and the one request over 1.2 s was
the measured maximum (2314 ms), so that bin spans 1.2-2.314 s. The histogram's mean is 0.86 s
(the thesis reports 867 ms: its bins hide their inner shape). Draws come from a generator
seeded once, so a run is reproducible.

Answers (thesis 5.4.5): 371 results for 147 images, so 1 + Poisson(1.52) results per lookup,
each of a category drawn from table 5.3 (text 32.3 %, logo 22.1 %, similar image 18.9 %, ...),
about one of the products of table 5.4. What a crop gets is a function of the seed and the
crop's pixels, as a real service answers the same image the same way.
"""

from __future__ import annotations

import asyncio
import zlib
from dataclasses import dataclass

import numpy as np

from . import Finding

LATENCY_BINS_S = (  # (from, to, requests): thesis table 5.6
    (0.504, 0.6, 3), (0.6, 0.7, 10), (0.7, 0.8, 33), (0.8, 0.9, 53), (0.9, 1.0, 31),
    (1.0, 1.1, 12), (1.1, 1.2, 4), (1.2, 2.314, 1),
)
CATEGORY_MIX = {  # thesis table 5.3, occurrences in 371 results
    "text": 120, "logo": 82, "similar_image": 70, "product": 42, "user_submitted": 35,
    "barcode": 14, "other": 8,
}
RESULTS_PER_LOOKUP = 371 / 147


@dataclass(frozen=True)
class _Product:
    name: str
    brand: str
    category: str
    words: tuple[str, ...]


PRODUCTS = (  # the objects of thesis table 5.4 and the words Goggles read on them
    _Product("Chio Chips Salt", "Chio", "snack", ("Chio", "Chips", "Salt")),
    _Product("Tullamore Dew Whiskey", "Tullamore Dew", "spirits", ("tullamore", "whiskey")),
    _Product("Weihenstephan H-Milch laktosefrei", "Weihenstephan", "dairy",
             ("Weihenstephan", "laktosefrei", "haltbar", "milch")),
    _Product("Kikkoman Sojasauce", "Kikkoman", "condiment", ("Kikkoman", "Sojasauce")),
    _Product("Barilla Aceto Balsamico", "Barilla", "condiment", ("Barilla", "Aceto", "Balsamico")),
    _Product("Kaba Traubenzucker", "Kaba", "sweets", ("Kaba", "Traubenzucker", "Vitamine")),
    _Product("Storck Knoppers", "Storck", "sweets", ("Knoppers", "Storck")),
    _Product("Lorenz Chipsletten Hot", "Lorenz", "snack", ("Lorenz", "Chipsletten", "Hot")),
)


def sample_latency_s(rng: np.random.Generator) -> float:
    """One lookup time in seconds, drawn from table 5.6."""
    counts = np.array([count for _, _, count in LATENCY_BINS_S], float)
    low, high, _ = LATENCY_BINS_S[rng.choice(len(counts), p=counts / counts.sum())]
    return float(rng.uniform(low, high))


def ean13(rng: np.random.Generator) -> str:
    """A random EAN-13 with a valid check digit."""
    digits = [int(d) for d in rng.integers(0, 10, 12)]
    check = (10 - sum(d * (3 if i % 2 else 1) for i, d in enumerate(digits)) % 10) % 10
    return "".join(map(str, digits)) + str(check)


def answer(crop: np.ndarray, seed: int) -> list[Finding]:
    """What the simulated service says about a crop: the same for the same crop and seed."""
    rng = np.random.default_rng([seed, zlib.crc32(np.ascontiguousarray(crop).tobytes())])
    product = PRODUCTS[rng.integers(len(PRODUCTS))]
    names, counts = zip(*CATEGORY_MIX.items(), strict=True)
    weights = np.array(counts, float) / sum(counts)
    height, width = crop.shape[:2]
    findings = []
    for _ in range(1 + rng.poisson(RESULTS_PER_LOOKUP - 1)):
        category = names[rng.choice(len(names), p=weights)]
        x, y = rng.uniform(0, 0.5, 2)
        w, h = rng.uniform(0.3, 1 - x), rng.uniform(0.3, 1 - y)
        box = tuple(round(float(v), 1) for v in (x * width, y * height, w * width, h * height))
        findings.append(_finding(category, product, box, rng))
    return findings


def _finding(category: str, product: _Product, box: tuple, rng: np.random.Generator) -> Finding:
    slug = product.name.lower().replace(" ", "-")
    link = f"https://lookup.invalid/{category}/{slug}"
    if category == "text":
        words = rng.permutation(product.words)[: rng.integers(1, len(product.words) + 1)]
        return Finding(category="text", title=" ".join(words), box=box)
    if category == "logo":
        return Finding(category="logo", title=product.brand, box=box, links=[link])
    if category == "product":
        return Finding(category="product", title=product.name, brand=product.brand, box=box,
                       links=[link], properties={"category": product.category})
    if category == "barcode":
        return Finding(category="barcode", title=ean13(rng), box=box)
    if category == "other":
        word = product.words[rng.integers(len(product.words))]
        return Finding(category="other", title=f"Translate: {word}", links=[link])
    label = "similar images" if category == "similar_image" else "user photo"
    return Finding(category=category, title=f"{product.name} ({label})", links=[link])


class SimulatedService:
    """The simulated lookup service: thesis latencies, thesis answers, seeded."""

    name = "simulated"

    def __init__(self, seed: int = 0):
        self.seed = seed
        self._latency = np.random.default_rng(seed)

    async def lookup(self, crop: np.ndarray) -> list[Finding]:
        await asyncio.sleep(sample_latency_s(self._latency))
        return answer(crop, self.seed)

    async def aclose(self) -> None:
        pass
