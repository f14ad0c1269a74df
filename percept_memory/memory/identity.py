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
- each cue enters as a likelihood ratio: how much likelier its value is for one object seen
  twice than for two different objects. Both distributions are learnt from the decisions as
  they are made (`Calibration`), so the model follows the real noise of the sensors, where
  the thesis learnt MLN weights offline from labelled data (6.2.3);
- the likelihood of each explanation: stay ~ look place staying, move ~ look prior_move,
  newview ~ place prior_newview staying; an object out of view can only have moved (formula
  6); of known objects that look alike beyond doubt, the move of the one seen last with that
  look is likelier; `staying`, the belief that an object is still where it was last seen,
  decays with the time since, at a rate learnt from the places looked at (`Dwell`);
- an object is known by every look it was seen with (`Known.others`), each kept by how many
  observations showed it (consolidation.py), so one wrong link adds a look but cannot make
  the object forget its own (Duceux 3.4.5: recognise on the stream of an object's views, not
  on one; Blodow 6.6: the memory remembers "how they look, where they usually stand, when and
  where they were seen the last time");
- "appear" and "unmatched" are options with their own likelihoods, so the assignment may
  prefer them to a poor match;
- for every new cluster the normalised likelihoods of all its alternatives are kept, so the
  API and the UI can show how sure the decision is.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from enum import StrEnum
from functools import cache, cached_property
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.special import gammainc

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
    # kitchen); the thesis' synthetic tables (noise up to 10 cm) used 0.25. Only a unit: how
    # near counts as "the same place" is learnt (Calibration).
    proximity_sigma: float = 0.05
    # Odds of the explanations, tuned on the thesis' synthetic protocol at its four noise
    # levels (bench/tune_identity.py, seed 1; bench/identity.py scores seed 0); prior_move
    # and prior_appear since on bench/belief.py's tune seeds (1001-1003, never reported).
    prior_move: float = 0.06  # odds that an object moved between two looks at it
    # odds that the same place shows another side of it; and of "an object in view is not
    # there any more": both re-tuned on bench/belief.py's tune seeds once the nearness of
    # different objects was learnt with its lower tail (DIFFERENT), which no longer makes any
    # place within 0.15 m e^12 times "the same" (were 0.3032 and 2.575)
    prior_newview: float = 1.0
    # odds of "a new object" against a known one: lower since the look odds of different
    # objects are learnt from scenes (bench/belief.py, tune seeds; was 4.1 on identity.py's),
    # and again (0.3) since their lower tail is (Histogram.log_density)
    prior_appear: float = 0.15
    prior_gone: float = 0.25
    # looks-the-same odds beyond which another known object is a lookalike (Decision), if it
    # looks at least 1/superseded as alike as the object decided on (one object remembered
    # twice looks as alike as itself; a look-alike of a crowded world less: with the odds
    # alone, tune seed 1001's crowded world of 105 objects seen ended with 95, merged; with
    # both, 99). The odds of different objects are learnt with a cautious lower tail
    # (Histogram.log_density), under which one object's own looks reach a few hundred at most
    # in its first scenes: at 1000, no object remembered twice was merged and strict
    # association fell from 96.3 to 90.7 % (tune seeds, sigma 0.025; 100: 95.0).
    lookalike_odds: float = 30.0
    # Of two known objects the new observation looks like beyond doubt (lookalike_odds), the
    # one seen last is likelier the one moved here: the move odds of one that looks no
    # likelier than another seen after it are divided by this. One object remembered twice
    # (two ids with its look, once given to objects seen side by side, so never merged) is
    # otherwise a coin flip each time it moves. Tuned on bench/belief.py's tune seeds.
    superseded: float = 4.0
    # Looks-the-same odds beyond which a new observation shows a look the object was seen with
    # (Decision.look): that look is refreshed; below, the observation is kept as a look of its
    # own, so a weak link (maybe a mistake) never replaces a look many observations agreed on.
    # (A stay refreshes the last look whatever its odds: the place vouches for it.) Tuned on
    # bench/belief.py's tune seeds (1, 10, 100 tried at sigma 0.025 and 0.05).
    same_look_odds: float = 10.0
    # Each annotator is wrong now and then (a shape misread, a colour under other light): one
    # disagreeing type weighs (a factor of at most 1/floor) but cannot veto the others, as it
    # would in a plain geometric mean (thesis 6.1.2).
    evidence_floor: float = 0.056
    # What the calibration believes before it has seen anything: the typical similarity and
    # proximity of two observations of one object, and of two different objects. Worth one
    # observation: a start, which the sensor's own data outweigh from the first scenes (a
    # heavier prior stays in the spread for hundreds of scenes and widens it). It then
    # follows the last `memory` observations.
    look_same: float = 0.9
    look_different: float = 0.2
    place_same: float = 0.9
    place_different: float = 0.1
    prior_weight: float = 1.0
    # ...and how long an object stays where it was put before it is believed to start, in
    # seconds (one prior_weight of a move in that long); the map's own rate is learnt.
    dwell_s: float = 3600.0
    memory: float = 500.0
    confident: float = 0.1424  # decisions at least this likely teach it what differs


@dataclass
class Observation:
    """What one observation says about an object: where it is and how it looks."""

    key: Any  # the cluster id (or any label)
    position: Vec | None
    evidence: Sequence[Annotation | Hypothesis] = ()
    # the variance of the position along each axis, when the sensor declares it
    # (Location.position_sigma; of an object's estimated place, that of the mean)
    position_variance: Vec | None = None

    @cached_property
    def by_type(self) -> dict[type, list]:
        """Its comparable evidence by type (grouped once: a remembered observation is
        compared with every scene that may show its object)."""
        return _by_type(self.evidence)

    def at(self, position: Vec | None, variance: Vec | None = None) -> Observation:
        """The same look at another place (sharing its grouped evidence)."""
        moved = replace(self, position=position, position_variance=variance)
        moved.__dict__["by_type"] = self.by_type
        return moved


@dataclass
class Known:
    """An object believed to exist, as last observed, and whether its place is in view now;
    `others`: the other looks it was seen with before (its other sides), so an object turned
    back, or moved showing a side seen before, is still recognised."""

    key: Any  # the object id
    last: Observation
    in_view: bool
    others: Sequence[Observation] = ()
    last_seen: int = 0  # when it was last seen (any clock; only the order counts)
    others_seen: Sequence[int] = ()  # when each of its other looks was last seen (default 0)


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
    # the key of the known look (Known.last or one of its others) the new observation looks
    # the same as beyond doubt (Parameters.same_look_odds); None for a look the object was not
    # seen with before, or one it only may have been
    look: Any = None
    # other known objects the new observation looks the same as beyond doubt, each with the
    # key of its look it matched: one of them may be this very object, remembered twice (see
    # consolidation.py's merge), or one that took this look by a wrong link
    lookalikes: dict = field(default_factory=dict)


def gaussian(distance: float, sigma: float) -> float:
    """Thesis eq. 6.1: 1 at distance 0, falling off with sigma."""
    return math.exp(-((distance / (2 * sigma)) ** 2))


def appearance(a: Sequence, b: Sequence, floor: float) -> float | None:
    """The geometric mean of the similarities of every evidence type both observations have
    (thesis 6.1.2), each at least `floor`; None when they share no comparable type."""
    value = float(looks([_by_type(a)], [_by_type(b)], floor)[0, 0])
    return None if math.isnan(value) else value


def _by_type(evidence: Sequence) -> dict[type, list]:
    """The evidence that can be compared, by type (in order of first appearance)."""
    grouped: dict[type, list] = {}
    for item in evidence:
        if _comparison(type(item)) is not None:
            grouped.setdefault(type(item), []).append(item)
    return grouped


@cache
def _comparison(kind: type) -> Callable | None:
    """How a type compares two lists of its items (a matrix, NaN where a pair does not
    compare): its own `similarities` (the built-in types, vectorised), else its `similarity`
    pair by pair; None when it compares nothing (the base's default)."""
    batch = getattr(kind, "similarities", None)
    if batch is not None:
        return batch
    pair = getattr(kind, "similarity", None)
    if pair is None or pair is Annotation.similarity:
        return None
    return lambda a, b: np.array([[pair(x, y) for y in b] for x in a], dtype=float
                                 ).reshape(len(a), len(b))


def similarities(kind: type, a: list, b: list) -> np.ndarray:
    """The similarity of every pair of items of one type, NaN where they do not compare."""
    return np.asarray(_comparison(kind)(a, b), dtype=float)


def looks(new: list[dict[type, list]], known: list[dict[type, list]], floor: float
          ) -> np.ndarray:
    """The appearance similarity of every (new, known) pair of observations, their evidence
    grouped by type: per type one similarity matrix; each piece of new evidence counts with
    its best match of its type on the other side; NaN where a pair shares no comparable type."""
    log_sum, count = np.zeros((len(new), len(known))), np.zeros((len(new), len(known)))
    shared = {kind for group in new for kind in group} & {kind for group in known for kind in group}
    bests, owners = [], []  # per type, per piece of new evidence: its best match per known
    for kind in sorted(shared, key=lambda k: (k.__module__, k.__qualname__)):
        rows = [(i, item) for i, group in enumerate(new) for item in group.get(kind, ())]
        cols = [(j, item) for j, group in enumerate(known) for item in group.get(kind, ())]
        values = similarities(kind, [item for _, item in rows], [item for _, item in cols])
        best = np.full((len(rows), len(known)), np.nan)  # per known observation its best item
        col_owners = np.array([j for j, _ in cols])  # ascending: cols are listed owner by owner
        starts = np.flatnonzero(np.diff(col_owners, prepend=-1))
        best[:, col_owners[starts]] = np.fmax.reduceat(values, starts, axis=1)
        bests.append(best)
        owners += [i for i, _ in rows]
    if bests:  # summed in one pass, in the same order as type by type
        best, owners = np.concatenate(bests), np.asarray(owners)
        compared = ~np.isnan(best)
        logs = np.log(np.clip(np.where(compared, best, 1.0), floor, 1.0))
        np.add.at(log_sum, owners, logs)
        np.add.at(count, owners, compared)
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, np.exp(log_sum / np.maximum(count, 1)), np.nan)


def _rows(vectors: Sequence[Vec | None]) -> np.ndarray:
    """Vectors of 3 as the rows of an array, NaN where one is unknown."""
    return np.array([v if v is not None else (np.nan,) * 3 for v in vectors],
                    dtype=float).reshape(len(vectors), 3)


def proximities(a: Sequence[Vec | None], b: Sequence[Vec | None], sigma: float) -> np.ndarray:
    """Eq. 6.1 of the distance of every pair of places, NaN where one is unknown."""
    with np.errstate(over="ignore", invalid="ignore"):  # places 1e308 apart: proximity 0
        distance = np.linalg.norm(_rows(a)[:, None, :] - _rows(b)[None, :, :], axis=-1)
        return np.exp(-((distance / (2 * sigma)) ** 2))


# --- calibration: how alike is "the same", learnt from the observations ---------------------

U_MIN = 1e-4  # -log similarity below this is "identical" (noise-free data)
LOG_ODDS_LIMIT = 12.0  # no single cue is surer than e^12 : 1


def surprise(similarity):
    """-log similarity (of a value or an array): 0 for identical, growing with distance (the
    squared distance over 4 sigma^2 for the Gaussian similarities of eq. 6.1)."""
    u = np.maximum(-np.log(np.maximum(similarity, 1e-300)), U_MIN)
    return float(u) if np.ndim(u) == 0 else u


@dataclass
class Spread:
    """The distribution of the surprise of one kind of pair, as a Gamma distribution (the
    squared distance under Gaussian noise is chi-squared, a Gamma) fitted by its running,
    slowly forgetting mean and variance."""

    weight: float
    mean: float
    variance: float

    @classmethod
    def around(cls, similarity: float, weight: float, shape: float) -> Spread:
        mean = surprise(similarity)
        return cls(weight, mean, mean * mean / shape)

    def learn(self, u: float, memory: float, weight: float = 1.0) -> None:
        """Take in one value, counted `weight` times (0..1: how sure it belongs here)."""
        if weight <= 0:
            return
        u = min(u, self.mean + 3 * math.sqrt(self.variance))  # an outlier widens it slowly
        self.weight = min(self.weight + weight, memory)
        delta = u - self.mean
        self.mean += weight * delta / self.weight
        self.variance += weight * (delta * (u - self.mean) - self.variance) / self.weight

    def gamma(self) -> tuple[float, float]:
        """Shape and scale, by the method of moments."""
        variance = max(self.variance, (self.mean * 0.05) ** 2, 1e-12)
        shape = min(max(self.mean * self.mean / variance, 0.3), 50.0)
        return shape, self.mean / shape

    def log_density(self, u):
        """Of a value or an array of them."""
        shape, scale = self.gamma()
        return ((shape - 1) * np.log(u) - u / scale - shape * math.log(scale)
                - math.lgamma(shape))


# the surprise axis in log steps, for the learnt spreads of different objects
EDGES = np.logspace(-4.0, 3.0, 71)  # 1e-4 .. 1e3, ten steps a decade
CENTRES = np.sqrt(EDGES[:-1] * EDGES[1:])


@dataclass(eq=False)
class Histogram:
    """The distribution of the surprise of pairs of different objects, learnt as a slowly
    forgetting histogram over log steps: its lower tail (different objects that happen to
    look alike, twins; or stand beside one's place) is what decides "moved here" against "a
    new object", and "turned" against "another one put there", and no simple family fits it
    (a Gamma fitted to the bulk makes a look-alike hundreds of times likelier to be the same
    object than it is, and any place within 0.15 m e^12 times)."""

    weight: float
    counts: np.ndarray

    def __post_init__(self) -> None:
        self.counts = np.asarray(self.counts, dtype=float)

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, Histogram) and self.weight == other.weight
                and np.array_equal(self.counts, other.counts))

    @classmethod
    def around(cls, similarity: float, weight: float, shape: float) -> Histogram:
        """A Gamma's shape, worth `weight` observations: a start the data outweigh."""
        mean = surprise(similarity)
        scale = mean / shape
        cdf = gammainc(shape, EDGES / scale)
        return cls(weight, weight * np.diff(cdf) / max(cdf[-1] - cdf[0], 1e-12))

    def learn_all(self, values: np.ndarray, memory: float) -> None:
        """Take in values, each counted once; beyond `memory` values the past fades."""
        if not len(values):
            return
        if self.weight + len(values) > memory:
            self.counts *= max(memory - len(values), 0.0) / self.weight
        np.add.at(self.counts, _step(values), 1.0)
        self.weight = float(self.counts.sum())

    def log_density(self, u):
        """Smoothed over neighbouring steps, never quite 0 (a value not met yet is rare, not
        impossible); below the lowest value met, as dense as there. Two different objects
        look alike by chance, and nearer alike ever more rarely; but how rarely, the few
        pairs seen early cannot say: with the floor there, a new object's look twice as far
        from a known one's as noise puts it was ~1,000 times likelier that object than
        another (bench/belief.py, the first 40 scenes of its tune seeds). Flat below the
        lowest seen, as a pair of two-dimensional looks would be, is the cautious guess (the
        colour cube's three would thin out faster), and the data replace it as it comes."""
        counts = np.convolve(self.counts, [0.25, 0.5, 0.25], mode="same")
        share = (counts + 1e-3 * max(self.weight, 1.0) / len(counts)) / (
            counts.sum() + 1e-3 * max(self.weight, 1.0))
        density = share / np.diff(EDGES)
        met = np.flatnonzero(counts >= 0.25)  # a value met, smoothed: 0.25 beside it
        if len(met):
            density[:met[0]] = density[met[0]]
        return np.log(density)[_step(u)]


def _step(u):
    return np.clip(np.searchsorted(EDGES, u, side="right") - 1, 0, len(CENTRES) - 1)


@dataclass
class Cue:
    """One kind of evidence (looks alike, is at the same place) as a likelihood ratio: how
    much likelier its value is for one object seen twice than for two different objects. Both
    distributions are learnt from the decisions, so the model follows the actual noise of the
    sensors instead of a fixed threshold (the thesis learnt its weights offline, 6.2.3)."""

    same: Spread
    different: Histogram | Spread

    def near(self, a: Vec, b: Vec, sigma: float, same: Spread | None = None) -> bool:
        """Whether two places lie as near as one object's observations do (within 3 standard
        deviations of the same-place spread: `same`, when the sensor declared it)."""
        same = same or self.same
        u = surprise(proximities([a], [b], sigma)[0, 0])
        return u <= same.mean + 3 * math.sqrt(same.variance)

    def odds(self, similarity, same: Spread | None = None):
        """The likelihood ratio of a similarity (or of an array of them, NaN or None where
        there is nothing to compare: no evidence either way, odds 1), against `same` instead
        of the learnt spread when given. Nearer is never less "the same" than farther: the
        ratio is made non-increasing in the surprise."""
        given = np.asarray(similarity, dtype=float)
        ratio = (same or self.same).log_density(CENTRES) - self.different.log_density(CENTRES)
        ratio = np.maximum.accumulate(ratio[::-1])[::-1]
        u = surprise(np.where(np.isnan(given), 1.0, given))
        log_odds = np.interp(np.log(u), np.log(CENTRES), ratio)
        odds = np.where(np.isnan(given), 1.0,
                        np.exp(np.clip(log_odds, -LOG_ODDS_LIMIT, LOG_ODDS_LIMIT)))
        return float(odds) if odds.ndim == 0 else odds


def declared_spread(variance: Vec, sigma: float) -> Spread:
    """The same-place spread of two observations of one object whose positions' noise is
    declared: the surprise of their distance, d^2 / 4 sigma^2 (eq. 6.1), where d^2 sums each
    axis' squared difference, of variance `variance` (both sides' summed). Its mean and
    variance are exact for Gaussian noise; a Gamma with them is exact when the axes' noise is
    alike (a chi-squared: shape 1 in the plane, 1.5 in space)."""
    unit = 4 * sigma * sigma
    mean = sum(variance) / unit
    return Spread(1.0, max(mean, U_MIN), 2 * sum(v * v for v in variance) / (unit * unit))


def _declared_place_odds(odds: np.ndarray, places: np.ndarray, new: Sequence[Observation],
                         known: Sequence[Known], calibration: Calibration, sigma: float) -> None:
    """Where both places' noise is declared, their place odds against the spread that noise
    gives (declared_spread) instead of the learnt one. The learnt spread is learnt from the
    decisions called "stay", and at high noise that loop keeps it narrow: an object's own
    observations 10 cm apart were then taken for a move (bench/belief.py at sigma 0.1)."""
    total = (_rows([o.position_variance for o in new])[:, None, :]
             + _rows([k.last.position_variance for k in known])[None, :, :])
    declared = ~np.isnan(total).any(axis=2)
    if not declared.any():
        return
    rows, cols = np.nonzero(declared)
    spreads, which = np.unique(total[declared].round(12), axis=0, return_inverse=True)
    for s, variance in enumerate(spreads):
        at = which.ravel() == s
        odds[rows[at], cols[at]] = calibration.place.odds(
            places[rows[at], cols[at]], declared_spread(tuple(variance), sigma))


# How alike different objects look is learnt from the pairs of clusters of each scene (sure
# to be different objects), how near another object lies from the confident decisions' other
# pairings (_learn); a histogram follows the lower tail of each: the look-alikes, and the
# objects beside one's place, among the bulk of other tables metres away.
DIFFERENT: dict[str, type] = {"look": Histogram, "place": Histogram}


@dataclass
class Dwell:
    """How long an object stays where it was seen: of `looks` at the believed places of
    objects in view, `left` found the object gone (moved or taken), over `watched` seconds
    since each was last seen; their ratio is the rate of an exponential dwell time (its
    maximum-likelihood estimate), learnt from the decisions like the cues and forgetting
    beyond `memory` looks. Belief in an unseen object's place decays with it: an object not
    seen for long is likelier moved, so another object found at its place is likelier another
    object than its other side (issue: stale candidates; Blodow 6.2.1 takes the place as
    evidence of the same object, true only while it is still there; 6.6: remembering "when
    and where they were seen the last time", and forgetting)."""

    left: float
    watched: float
    looks: float

    @classmethod
    def prior(cls, params: Parameters) -> Dwell:
        """The prior dwell time as a hundredth of a departure over a hundredth of it, so
        the first looks' seconds outweigh it (a whole one would be an hour's watching)."""
        return cls(params.prior_weight / 100, params.prior_weight * params.dwell_s / 100,
                   params.prior_weight)

    def staying(self, elapsed_s: float) -> float:
        """The probability an object is still where it was seen `elapsed_s` seconds ago."""
        return math.exp(-self.left / max(self.watched, 1e-9) * max(elapsed_s, 0.0))

    def learn(self, left: bool, elapsed_s: float, memory: float) -> None:
        """One look at an object's believed place: it had left it, or it had not."""
        fade = min(1.0, (memory - 1.0) / max(self.looks, 1.0))
        self.left = self.left * fade + left
        self.watched = self.watched * fade + max(elapsed_s, 0.0)
        self.looks = self.looks * fade + 1.0


@dataclass
class Calibration:
    """What the model has learnt about its sensors and its world; kept across scenes (and
    stored)."""

    look: Cue
    place: Cue
    dwell: Dwell

    @classmethod
    def prior(cls, params: Parameters) -> Calibration:
        def cue(same: float, different: float, kind: type) -> Cue:
            # one object seen twice: a chi-squared-like spread from 0; two objects: rarely
            # anywhere near identical
            return Cue(Spread.around(same, params.prior_weight, shape=1.5),
                       kind.around(different, params.prior_weight, shape=4.0))

        return cls(look=cue(params.look_same, params.look_different, DIFFERENT["look"]),
                   place=cue(params.place_same, params.place_different, DIFFERENT["place"]),
                   dwell=Dwell.prior(params))

    def to_document(self) -> dict:
        return {**{name: {side: {k: v.tolist() if isinstance(v, np.ndarray) else v
                                 for k, v in vars(getattr(getattr(self, name), side)).items()}
                          for side in ("same", "different")} for name in ("look", "place")},
                "dwell": vars(self.dwell)}

    @classmethod
    def from_document(cls, doc: dict) -> Calibration:
        """(What a calibration stored by an older release learnt in another form, the dwell
        time or a spread now learnt as a histogram, starts from its prior.)"""
        prior = cls.prior(Parameters())

        def different(name: str, kind: type):
            stored = doc[name]["different"]
            return (kind(**stored) if set(stored) == {f.name for f in fields(kind)}
                    else getattr(prior, name).different)

        return cls(**{name: Cue(Spread(**doc[name]["same"]), different(name, kind))
                      for name, kind in DIFFERENT.items()},
                   dwell=Dwell(**doc["dwell"]) if "dwell" in doc else prior.dwell)


def explanations(look: float, place: float, in_view: bool, params: Parameters,
                 other: float = 0.0, superseded: bool = False, staying: float = 1.0) -> dict:
    """Likelihood of each way the new observation could be the known object, relative to its
    being another object, from the odds of "looks the same" (as it last looked; `other`: as
    the best of its other known looks) and "is at the same place"; `superseded`: another
    candidate seen after it looks at least as alike, beyond doubt; `staying`: the
    probability it is still where it was seen (Dwell). Turned to a side seen before is
    likelier than to a side never seen."""
    seen = max(look, other)
    move = seen * params.prior_move / (params.superseded if superseded else 1.0)
    if not in_view:  # its old place is not seen now: it can only have been moved here
        return {Explanation.MOVE: move}
    return {
        Explanation.STAY: look * place * staying,
        Explanation.MOVE: move,
        # turned to a side seen before: as much likelier as that side fits better than the
        # last one (a look kept twice is no other side to turn to)
        Explanation.NEWVIEW: place * params.prior_newview * max(other / max(look, 1.0), 1.0)
        * staying,
    }


def resolve(new: Sequence[Observation], known: Sequence[Known],
            params: Parameters | None = None,
            calibration: Calibration | None = None,
            apart: Mapping[Any, Collection] | None = None, now: int | None = None
            ) -> list[Decision]:
    """One joint decision for a scene: a Decision per new observation (in order), then one
    per known object left unmatched (hidden or disappear). A `calibration` kept by the caller
    learns from the confident decisions; without one, the prior calibration is used.
    `apart`: observation key -> the known objects a person said it is not (no likelihood).
    `now`: the scene's time in ns, on the clock of the candidates' `last_seen` (None: places
    never go stale)."""
    params = params or Parameters()
    calibration = calibration or Calibration.prior(params)
    # the cues of every pair, then their odds at once; the new observations with each other
    # too (one scene's clusters are different objects: _learn)
    groups = [o.by_type for o in new]
    looked = looks(groups, [k.last.by_type for k in known] + groups,
                   params.evidence_floor)
    looked, looked_apart = looked[:, :len(known)], looked[:, len(known):]
    places = proximities([o.position for o in new], [k.last.position for k in known],
                         params.proximity_sigma)
    look_odds = calibration.look.odds(looked.reshape(len(new), len(known)))
    place_odds = calibration.place.odds(places.reshape(len(new), len(known)))
    _declared_place_odds(place_odds, places, new, known, calibration, params.proximity_sigma)
    other_odds, other_look, other_seen = _other_looks(new, known, calibration, params)
    seen = np.where(look_odds >= other_odds, np.array([k.last_seen for k in known]),
                    other_seen)
    superseded = _superseded(np.maximum(look_odds, other_odds), seen, params.lookalike_odds)
    elapsed_s = [0.0 if now is None else (now - k.last_seen) / 1e9 for k in known]
    staying = [calibration.dwell.staying(e) for e in elapsed_s]
    likelihood = np.zeros((len(new), len(known)))
    best: dict[tuple[int, int], Explanation] = {}
    table: list[list[dict]] = []
    for i in range(len(new)):
        row = []
        for j, candidate in enumerate(known):
            ways = explanations(float(look_odds[i, j]), float(place_odds[i, j]),
                                candidate.in_view, params, float(other_odds[i, j]),
                                bool(superseded[i, j]), staying[j])
            row.append(ways)
            best[i, j] = max(ways, key=ways.get)
            likelihood[i, j] = ways[best[i, j]]
        for j in _kept_apart(new[i], known, apart):
            row[j] = dict.fromkeys(row[j], 0.0)
            likelihood[i, j] = 0.0
        table.append(row)
    gone = [params.prior_gone if k.in_view else 1.0 for k in known]  # hidden costs nothing
    assigned = _assign(likelihood, params.prior_appear, gone)

    decisions = []
    matched: set[int] = set()
    taken = set(assigned.values())
    for i, observation in enumerate(new):
        alternatives = _alternatives(table[i], known, params.prior_appear, gone,
                                     taken - {assigned.get(i)})
        j = assigned.get(i)
        if j is None:
            decisions.append(Decision(observation.key, None, Explanation.APPEAR,
                                      _probability(alternatives, None, Explanation.APPEAR),
                                      alternatives))
            continue
        matched.add(j)
        explanation = best[i, j]
        look = (known[j].last.key if explanation is Explanation.STAY  # its last look, by place
                else None if max(look_odds[i, j], other_odds[i, j]) < params.same_look_odds
                else known[j].last.key if look_odds[i, j] >= other_odds[i, j]
                else other_look[i][j])
        odds = np.maximum(look_odds[i], other_odds[i])
        alike = (odds >= params.lookalike_odds) & (odds * params.superseded >= odds[j])
        decisions.append(Decision(observation.key, known[j].key, explanation,
                                  _probability(alternatives, known[j].key, explanation),
                                  alternatives, look,
                                  {known[k].key: known[k].last.key if look_odds[i, k]
                                   >= other_odds[i, k] else other_look[i][k]
                                   for k in np.flatnonzero(alike) if k != j}))
    for j, candidate in enumerate(known):
        if j not in matched:
            explanation = Explanation.DISAPPEAR if candidate.in_view else Explanation.HIDDEN
            decisions.append(Decision(candidate.key, candidate.key, explanation, 1.0))
    _learn(calibration, decisions[:len(new)], assigned, looked, places, looked_apart, params)
    if now is not None:
        _learn_dwell(calibration.dwell, decisions, known, elapsed_s, params)
    return decisions


def _kept_apart(observation: Observation, known: Sequence[Known],
                apart: Mapping[Any, Collection] | None) -> list[int]:
    """The known objects a person said the observation is not (types/curation.py)."""
    said = (apart or {}).get(observation.key, ())
    return [j for j, candidate in enumerate(known) if candidate.key in said]


def _superseded(alike: np.ndarray, seen: np.ndarray, beyond_doubt: float) -> np.ndarray:
    """For every (new, known) pair whether another known object looks at least as alike, with
    odds beyond doubt, by a look seen after the one of that object it looks like (`alike`: the
    looks' odds; `seen`: when the look each pair compared best with was last seen). Where
    a look was last seen is where its object went: an object that took that look once by a
    wrong link, and was seen since with its own, is not the one seen last with it."""
    later = seen[:, None, :] > seen[:, :, None]  # [i, j, k]: k's look was seen after j's
    sure = alike >= beyond_doubt
    return np.any(later & sure[:, None, :] & (alike[:, None, :] >= alike[:, :, None]), axis=2)


def _other_looks(new: Sequence[Observation], known: Sequence[Known],
                 calibration: Calibration, params: Parameters
                 ) -> tuple[np.ndarray, list, np.ndarray]:
    """For every (new, known) pair, the odds that the new one looks the same as the best of
    the known object's other looks, that look's key, and when that look was last seen; 0,
    None and 0 where it has none (no other look makes a move or a turn likelier: with odds
    of 1, an object that looks nothing like the new observation was as likely moved here
    as one that looks like it)."""
    odds = np.zeros((len(new), len(known)))
    seen = np.zeros((len(new), len(known)))
    keys: list[list] = [[None] * len(known) for _ in new]
    others = [(j, other, when) for j, k in enumerate(known)
              for other, when in zip(k.others, k.others_seen or [0] * len(k.others),
                                     strict=True)]
    if not others or not new:
        return odds, keys, seen
    looked = looks([o.by_type for o in new], [o.by_type for _, o, _ in others],
                   params.evidence_floor)
    each = calibration.look.odds(looked)
    for c, (j, other, when) in enumerate(others):
        for i in np.flatnonzero(each[:, c] > odds[:, j]):
            odds[i, j] = each[i, c]
            keys[i][j] = other.key
            seen[i, j] = when
    return odds, keys, seen


def _learn(calibration: Calibration, decisions: list[Decision], assigned: dict[int, int],
           looked: np.ndarray, places: np.ndarray, looked_apart: np.ndarray,
           params: Parameters) -> None:
    """Teach the calibration (soft EM, thesis 6.2.3 learnt offline): a stay shows how alike
    and how near one object seen twice is, each cue's value counted by how sure the current
    model is that it belongs to the same object rather than to a turned (newview) or moved
    one, so a wrong stay cannot widen what "the same" means. Two clusters of one scene are
    two different objects for sure (`looked_apart`: the scene's clusters with each other):
    every such pair shows how alike different objects look, with no decision in the loop to
    teach a mistake back to the model; how near another object lies from one's place is
    learnt from the confident decisions' other pairings."""
    memory = params.memory
    with np.errstate(invalid="ignore"):
        look_u, place_u = surprise(looked), surprise(places)
    for i, decision in enumerate(decisions):
        j = assigned.get(i)
        if j is not None and decision.explanation is Explanation.STAY:
            if not math.isnan(look := float(look_u[i, j])):
                odds = calibration.look.odds(looked[i, j]) / params.prior_newview
                calibration.look.same.learn(look, memory, odds / (1 + odds))
            if not math.isnan(place := float(place_u[i, j])):
                odds = calibration.place.odds(places[i, j]) / params.prior_move
                calibration.place.same.learn(place, memory, odds / (1 + odds))
        if decision.probability >= params.confident:
            others = np.flatnonzero(~np.isnan(place_u[i]))
            calibration.place.different.learn_all(place_u[i, others[others != j]], memory)
    alike = surprise(looked_apart[np.triu_indices_from(looked_apart, 1)])
    calibration.look.different.learn_all(alike[~np.isnan(alike)], memory)


def _learn_dwell(dwell: Dwell, decisions: list[Decision], known: Sequence[Known],
                 elapsed_s: list[float], params: Parameters) -> None:
    """Every object whose believed place is in view was looked for there: found (stay,
    newview) or not (moved elsewhere, gone), after the time since it was last seen; the
    confident decisions teach the dwell time."""
    index = {k.key: j for j, k in enumerate(known)}
    for decision in decisions:
        j = index.get(decision.object)
        if j is None or not known[j].in_view or decision.probability < params.confident:
            continue
        dwell.learn(decision.explanation not in (Explanation.STAY, Explanation.NEWVIEW),
                    elapsed_s[j], params.memory)


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
                  gone: list[float], taken: set[int]) -> list[Alternative]:
    """Every way to explain one new observation, with normalised probabilities, best first,
    given what the scene's other observations are (`taken`: the known objects they were
    found to be are none of this one's ways: a bottle seen beside the one that stayed is
    not that one moved, however alike). Weighted as the assignment weighs them: being an
    object in view also spares that object the unlikely "it is gone"."""
    options = [Alternative(None, Explanation.APPEAR, appear)]
    for j, (ways, candidate, unmatched) in enumerate(zip(row, known, gone, strict=True)):
        if j not in taken:
            options += [Alternative(candidate.key, e, value / unmatched)
                        for e, value in ways.items() if value]
    total = sum(o.probability for o in options)
    for option in options:
        option.probability /= total
    return sorted(options, key=lambda o: o.probability, reverse=True)


def _probability(alternatives: list[Alternative], obj: Any, explanation: Explanation) -> float:
    return next((a.probability for a in alternatives
                 if a.object == obj and a.explanation == explanation), 0.0)
