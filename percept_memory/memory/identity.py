"""Identity resolution: which new observation is which known object, and what happened.

Blodow's thesis (chapter 6) decides, per scene, for every new cluster n and every object o
believed to exist: stay (o and n look alike, same place), move (alike, elsewhere), newview
(same place, different look: another side), or not; new clusters matched to nothing appear,
objects matched to nothing are hidden when their place is out of view and disappeared when it
was in view (6.2.1). The thesis solved this with a Markov logic network, too slow for real
time. Here the same model is one joint assignment (Hungarian algorithm), so the decision is
globally consistent (no object claimed twice) and runs in milliseconds:

- evidence: appearance similarity `s` from the annotation types both observations share
  (each type's `similarity`, combined by their geometric mean, thesis 6.1.2) and proximity
  `p = g(distance)` with the thesis' g(x) = exp(-(x / 2 sigma)^2) (eq. 6.1);
- the likelihood of each explanation: stay ~ s p, move ~ s (1 - p) prior_move,
  newview ~ (1 - s) p prior_newview; an object out of view can only have moved (formula 6);
- "appear" and "unmatched" are options with their own likelihoods, so the assignment may
  prefer them to a poor match;
- for every new cluster the normalised likelihoods of all its alternatives are kept, so the
  API and the UI can show how sure the decision is.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from .types import Annotation, Hypothesis

Vec = tuple[float, float, float]


class Explanation(StrEnum):
    STAY = "stay"
    MOVE = "move"
    NEWVIEW = "newview"
    APPEAR = "appear"
    HIDDEN = "hidden"
    DISAPPEAR = "disappear"


@dataclass(frozen=True)
class Parameters:
    """The model's knobs; the defaults come from bench/identity.py (thesis protocol)."""

    # m: 2-3x the noise of a position (robot localisation + segmentation, about 2 cm in the
    # kitchen); the thesis' synthetic tables (noise up to 10 cm) used 0.25
    proximity_sigma: float = 0.05
    # The rest tuned on the thesis' synthetic protocol (bench/tune_identity.py, noise 0.025 and
    # 0.05, seed 1; bench/identity.py scores seed 0).
    prior_move: float = 0.049  # odds that an object moved between two looks at it
    prior_newview: float = 0.31  # odds that the same place shows another side of it
    prior_appear: float = 1.33  # odds of "a new object" against a known one
    prior_gone: float = 0.79  # odds of "an object in view is not there any more"
    unknown_similarity: float = 0.5  # when two observations share no comparable evidence
    look_threshold: float = 0.70  # appearance similarity at which "same look" is even odds
    look_sharpness: float = 16.3
    place_threshold: float = 0.76  # proximity at which "same place" is even odds
    place_sharpness: float = 7.76
    # Each annotator is wrong now and then (a shape misread, a colour under other light): one
    # disagreeing type weighs (a factor of at most 1/floor) but cannot veto the others, as it
    # would in a plain geometric mean (thesis 6.1.2).
    evidence_floor: float = 0.056


@dataclass
class Observation:
    """What one observation says about an object: where it is and how it looks."""

    key: Any  # the cluster id (or any label)
    position: Vec | None
    evidence: Sequence[Annotation | Hypothesis] = ()


@dataclass
class Known:
    """An object believed to exist, as last observed, and whether its place is in view now."""

    key: Any  # the object id
    last: Observation
    in_view: bool


@dataclass
class Alternative:
    object: Any  # object key, or None for "a new object"
    explanation: Explanation
    probability: float


@dataclass
class Decision:
    """What became of one new observation or one known object."""

    key: Any  # observation key (new) or object key (known, unmatched)
    object: Any  # the object it is (None: a new object, to be created)
    explanation: Explanation
    probability: float
    alternatives: list[Alternative] = field(default_factory=list)


def gaussian(distance: float, sigma: float) -> float:
    """Thesis eq. 6.1: 1 at distance 0, falling off with sigma."""
    return math.exp(-((distance / (2 * sigma)) ** 2))


def appearance(a: Sequence, b: Sequence, default: float, floor: float) -> float:
    """The geometric mean of the similarities of every evidence type both observations have
    (thesis 6.1.2), each at least `floor`; `default` when they share no comparable type."""
    by_type: dict[type, list] = {}
    for item in b:
        by_type.setdefault(type(item), []).append(item)
    scores = []
    for item in a:  # each piece of evidence counts with its best match of the same type
        similarity: Callable | None = getattr(type(item), "similarity", None)
        values = [similarity(item, other) for other in by_type.get(type(item), ())
                  ] if similarity else []
        values = [v for v in values if v is not None]
        if values:
            scores.append(min(max(float(max(values)), floor), 1.0))
    if not scores:
        return default
    return float(np.exp(np.mean(np.log(scores))))


def proximity(a: Vec | None, b: Vec | None, sigma: float) -> float:
    if a is None or b is None:
        return 0.5
    return gaussian(float(np.linalg.norm(np.subtract(a, b))), sigma)


def explanations(similarity: float, near: float, in_view: bool, params: Parameters) -> dict:
    """Likelihood of each way the new observation could be the known object, relative to its
    being another object: each piece of evidence as calibrated odds, exp(k (x - threshold)),
    so "looks the same" and "is at the same place" are judged against thresholds tuned on
    data rather than taken at face value."""
    look = math.exp(params.look_sharpness * (similarity - params.look_threshold))
    if not in_view:  # its old place is not seen now: it can only have been moved here
        return {Explanation.MOVE: look * params.prior_move}
    place = math.exp(params.place_sharpness * (near - params.place_threshold))
    return {
        Explanation.STAY: look * place,
        Explanation.MOVE: look * params.prior_move,
        Explanation.NEWVIEW: place * params.prior_newview,
    }


def resolve(new: Sequence[Observation], known: Sequence[Known],
            params: Parameters | None = None) -> list[Decision]:
    """One joint decision for a scene: a Decision per new observation (in order), then one
    per known object left unmatched (hidden or disappear)."""
    params = params or Parameters()
    likelihood = np.zeros((len(new), len(known)))
    best: dict[tuple[int, int], Explanation] = {}
    table: list[list[dict]] = []
    for i, observation in enumerate(new):
        row = []
        for j, candidate in enumerate(known):
            s = appearance(observation.evidence, candidate.last.evidence,
                           params.unknown_similarity, params.evidence_floor)
            p = proximity(observation.position, candidate.last.position, params.proximity_sigma)
            ways = explanations(s, p, candidate.in_view, params)
            row.append(ways)
            best[i, j] = max(ways, key=ways.get)
            likelihood[i, j] = ways[best[i, j]]
        table.append(row)
    gone = [params.prior_gone if k.in_view else 1.0 for k in known]  # hidden costs nothing
    assigned = _assign(likelihood, params.prior_appear, gone)

    decisions = []
    matched: set[int] = set()
    for i, observation in enumerate(new):
        alternatives = _alternatives(table[i], known, params.prior_appear, gone)
        j = assigned.get(i)
        if j is None:
            decisions.append(Decision(observation.key, None, Explanation.APPEAR,
                                      _probability(alternatives, None, Explanation.APPEAR),
                                      alternatives))
            continue
        matched.add(j)
        explanation = best[i, j]
        decisions.append(Decision(observation.key, known[j].key, explanation,
                                  _probability(alternatives, known[j].key, explanation),
                                  alternatives))
    for j, candidate in enumerate(known):
        if j not in matched:
            explanation = Explanation.DISAPPEAR if candidate.in_view else Explanation.HIDDEN
            decisions.append(Decision(candidate.key, candidate.key, explanation, 1.0))
    return decisions


def _assign(likelihood: np.ndarray, appear: float, gone: list[float]) -> dict[int, int]:
    """Maximum-likelihood matching with "appear" for each new and "unmatched" for each known
    observation: the classic augmented square cost matrix of -log likelihoods."""
    n, m = likelihood.shape
    impossible = 1e9
    cost = np.full((n + m, m + n), impossible)
    cost[:n, :m] = -np.log(np.maximum(likelihood, 1e-300))
    cost[:n, m:] = np.where(np.eye(n, dtype=bool), -math.log(appear), impossible)
    cost[n:, :m] = np.where(np.eye(m, dtype=bool), -np.log(np.maximum(gone, 1e-300)), impossible)
    cost[n:, m:] = 0.0
    rows, cols = linear_sum_assignment(cost)
    return {int(r): int(c) for r, c in zip(rows, cols, strict=True)
            if r < n and c < m and cost[r, c] < impossible}


def _alternatives(row: list[dict], known: Sequence[Known], appear: float,
                  gone: list[float]) -> list[Alternative]:
    """Every way to explain one new observation, with normalised probabilities, best first.
    Weighted as the assignment weighs them: being an object in view also spares that object
    the unlikely "it is gone"."""
    options = [Alternative(None, Explanation.APPEAR, appear)]
    for ways, candidate, unmatched in zip(row, known, gone, strict=True):
        options += [Alternative(candidate.key, e, value / unmatched)
                    for e, value in ways.items() if value]
    total = sum(o.probability for o in options)
    for option in options:
        option.probability /= total
    return sorted(options, key=lambda o: o.probability, reverse=True)


def _probability(alternatives: list[Alternative], obj: Any, explanation: Explanation) -> float:
    return next((a.probability for a in alternatives
                 if a.object == obj and a.explanation == explanation), 0.0)
