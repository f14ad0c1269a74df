"""The pure identity decision core (memory/identity.py): thesis figure 6.9 and the introduction's
three cups, with our own annotation types and positions in metres. No database."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from percept_memory.memory.identity import (
    Calibration,
    Explanation,
    Known,
    Observation,
    Parameters,
    appearance,
    resolve,
)
from percept_memory.memory.types import (
    Classification,
    ColorHistogram,
    SemanticColor,
    Shape,
    Text,
)

# The default Parameters: priors tuned on the thesis' synthetic protocol
# (bench/tune_identity.py), proximity sigma for kitchen positions (good to about 2 cm).
DEFAULTS = Parameters()

STAY, MOVE, NEWVIEW = Explanation.STAY, Explanation.MOVE, Explanation.NEWVIEW
APPEAR, HIDDEN, DISAPPEAR = Explanation.APPEAR, Explanation.HIDDEN, Explanation.DISAPPEAR


def histogram(peaks: dict[int, float], bins: int = 16) -> ColorHistogram:
    values = np.full(bins, 0.01)
    for index, weight in peaks.items():
        values[index] += weight
    return ColorHistogram(histogram=values / values.sum(), space="H")


def plate():
    return [Shape(shape="flat"), Classification(class_name="plate"),
            SemanticColor(ratios={"white": 0.9, "grey": 0.1}), histogram({0: 1.0})]


def ice_tea(flavour: str, green: float):
    return [Shape(shape="box"), Classification(class_name="tetrapak"),
            SemanticColor(ratios={"green": green, "white": 0.3, "yellow": 0.7 - green}),
            Text(text=f"ICE TEA {flavour}"), histogram({5: green, 3: 1 - green})]


def magazine():
    return [Shape(shape="flat"), Classification(class_name="magazine"),
            SemanticColor(ratios={"red": 0.5, "white": 0.4, "black": 0.1}),
            Text(text="KITCHEN weekly special"), histogram({0: 0.6, 15: 0.4})]


def cup():
    return [Shape(shape="cylinder"), Classification(class_name="cup"),
            SemanticColor(ratios={"blue": 0.8, "white": 0.2}), histogram({10: 1.0})]


def obs(key, x: float, y: float, evidence) -> Observation:
    return Observation(key, (x, y, 0.8), evidence)


def known(key, x: float, y: float, evidence, in_view: bool = True) -> Known:
    return Known(key, obs(f"old-{key}", x, y, evidence), in_view)


def outcome(decisions) -> dict:
    return {d.key: (d.object, d.explanation) for d in decisions}


def test_two_identical_plates_are_kept_apart_by_position():
    """Figure 6.9, first scene: one plate stays, the other is moved 30 cm: no swap."""
    before = [known("A", 0.0, 0.0, plate()), known("B", 0.4, 0.0, plate())]
    now = [obs("n1", 0.01, -0.005, plate()), obs("n2", 0.4, 0.3, plate())]
    assert outcome(resolve(now, before, DEFAULTS)) == {"n1": ("A", STAY), "n2": ("B", MOVE)}


def test_magazine_gone_and_a_second_ice_tea_appears():
    """Figure 6.9, second scene: the ice tea stays, the magazine disappears, and a new ice tea
    much like the first appears elsewhere (neither the old ice tea nor the magazine)."""
    before = [known("tea", 0.0, 0.0, ice_tea("peach", 0.5)),
              known("magazine", 0.35, 0.2, magazine()),
              known("mug", 0.7, 0.0, cup())]
    now = [obs("n-tea", 0.008, 0.004, ice_tea("peach", 0.5)),
           obs("n-mug", 0.69, 0.01, cup()),
           obs("n-tea2", 0.3, -0.3, ice_tea("lemon", 0.45))]
    assert outcome(resolve(now, before, DEFAULTS)) == {
        "n-tea": ("tea", STAY), "n-mug": ("mug", STAY), "n-tea2": (None, APPEAR),
        "magazine": ("magazine", DISAPPEAR)}


def test_three_identical_cups_the_middle_one_taken_while_looking_away():
    """The introduction's three cups: taken while out of view, the middle cup is believed
    hidden; looking again, the two others stay (each the right one) and it disappears."""
    cups = [known(name, x, 0.0, cup()) for name, x in (("left", 0.0), ("middle", 0.15),
                                                       ("right", 0.3))]
    now = [obs("n-left", 0.0, 0.0, cup()), obs("n-middle", 0.15, 0.0, cup()),
           obs("n-right", 0.3, 0.0, cup())]
    first = outcome(resolve(now, cups, DEFAULTS))
    assert first == {"n-left": ("left", STAY), "n-middle": ("middle", STAY),
                     "n-right": ("right", STAY)}

    away = [Known(c.key, c.last, in_view=False) for c in cups]  # the robot looks elsewhere
    assert outcome(resolve([], away, DEFAULTS)) == {c.key: (c.key, HIDDEN) for c in cups}

    again = [obs("m-left", 0.008, -0.006, cup()), obs("m-right", 0.295, 0.01, cup())]
    assert outcome(resolve(again, cups, DEFAULTS)) == {
        "m-left": ("left", STAY), "m-right": ("right", STAY), "middle": ("middle", DISAPPEAR)}


def test_a_hidden_object_moved_into_view_is_a_move():
    before = [known("tea", 2.0, 1.0, ice_tea("peach", 0.5), in_view=False),
              known("mug", 0.0, 0.0, cup())]
    now = [obs("n-mug", 0.005, 0.0, cup()), obs("n-tea", 0.4, 0.1, ice_tea("peach", 0.5))]
    assert outcome(resolve(now, before, DEFAULTS)) == {"n-mug": ("mug", STAY),
                                                   "n-tea": ("tea", MOVE)}


def test_a_declared_position_noise_widens_the_same_place():
    """A sensor good to 10 cm that says so (Location.position_sigma): an object's own
    observation 12 cm from its place is at the same place, where the spread learnt for a
    sensor good to 2 cm (the prior) calls it moved; at 1 m it is moved either way."""
    noisy = (0.01, 0.01, 0.0)  # variance: 10 cm along x and y

    def decide(x: float, variance) -> Explanation:
        before = [Known("mug", replace(obs("old", 0.0, 0.0, cup()), position_variance=variance),
                        True)]
        now = [replace(obs("n", x, 0.05, cup()), position_variance=variance)]
        return resolve(now, before, DEFAULTS)[0].explanation

    assert (decide(0.11, None), decide(0.11, noisy)) == (MOVE, STAY)
    assert (decide(1.0, None), decide(1.0, noisy)) == (MOVE, MOVE)


def test_an_object_that_looks_nothing_like_it_was_not_moved_here():
    """A move needs the look: an object out of view that looks nothing like the new
    observation, with no other look known, is no likelier moved here than a magazine that is
    a cup (before, its missing other looks counted as odds 1, so every such object held a
    move's prior: a tenth of the decision's probability went to them)."""
    others = [known(f"magazine-{k}", 3.0 + k, 0.0, magazine(), in_view=False) for k in range(5)]
    decision = resolve([obs("n", 0.0, 0.0, cup())], others, DEFAULTS)[0]
    assert (decision.object, decision.explanation) == (None, APPEAR)
    assert decision.probability > 0.999
    assert all(a.probability < 1e-3 for a in decision.alternatives[1:])


def test_a_lookalike_beside_the_one_that_stayed_is_surely_new():
    """The confidence is given what the scene's other observations are: the known cup stayed,
    so the second cup is new (its own row alone made it the cup moved, and the right
    decision came out at 0.0003)."""
    before = [known("cup", 0.0, 0.0, cup())]
    stayed, beside = resolve([obs("a", 0.0, 0.0, cup()), obs("b", 0.4, 0.0, cup())], before,
                             DEFAULTS)[:2]
    assert (stayed.object, stayed.explanation, beside.explanation) == ("cup", STAY, APPEAR)
    assert beside.probability > 0.99
    assert {a.object for a in beside.alternatives} == {None}  # the cup is the other one


def test_of_two_lookalikes_the_one_seen_last_is_the_one_moved_here():
    """One object remembered twice: both ids have its look. Moved again, it is the id seen
    last, not a coin flip."""
    older = Known("older", obs("old-older", 0.0, 0.0, cup()), False, last_seen=1)
    later = Known("later", obs("old-later", 3.0, 0.0, cup()), False, last_seen=2)
    now = [obs("n", 0.5, 0.3, cup())]
    decided = outcome(resolve(now, [older, later], DEFAULTS))
    assert decided["n"] == ("later", MOVE)
    assert outcome(resolve(now, [older, later], replace(DEFAULTS, superseded=1.0)))["n"] == (
        "older", MOVE)  # without the rule: the first of a tie


def test_a_turned_object_is_a_new_view():
    front = [Shape(shape="box"), Classification(class_name="cereal box"),
             SemanticColor(ratios={"yellow": 0.6, "red": 0.3, "white": 0.1}),
             Text(text="CORN FLAKES"), histogram({2: 0.7, 0: 0.3})]
    back = [Shape(shape="box"), Classification(class_name="cereal box"),
            SemanticColor(ratios={"white": 0.7, "blue": 0.3}),
            Text(text="nutrition facts per 100 g"), histogram({10: 0.6, 8: 0.4})]
    before = [known("box", 0.5, 0.2, front), known("mug", 0.0, 0.0, cup())]
    now = [obs("n-mug", 0.0, 0.004, cup()), obs("n-box", 0.51, 0.195, back)]
    assert outcome(resolve(now, before, DEFAULTS)) == {"n-mug": ("mug", STAY),
                                                   "n-box": ("box", NEWVIEW)}


KINDS = [plate, cup, magazine, lambda: ice_tea("peach", 0.5), lambda: ice_tea("lemon", 0.4)]


@pytest.mark.parametrize("seed", range(30))
def test_decisions_are_globally_consistent(seed):
    rng = np.random.default_rng(seed)

    def random_evidence():
        return KINDS[int(rng.integers(len(KINDS)))]()

    before = [known(f"o{j}", *rng.uniform(0, 1, 2), random_evidence(),
                    in_view=bool(rng.random() < 0.6)) for j in range(int(rng.integers(0, 8)))]
    now = [obs(f"n{i}", *rng.uniform(0, 1, 2), random_evidence())
           for i in range(int(rng.integers(0, 8)))]
    decisions = resolve(now, before, DEFAULTS)

    assert [d.key for d in decisions[:len(now)]] == [n.key for n in now]
    claimed = [d.object for d in decisions[:len(now)] if d.object is not None]
    assert len(claimed) == len(set(claimed))  # no object claimed twice
    rest = decisions[len(now):]
    assert {d.key for d in rest} == {k.key for k in before} - set(claimed)
    in_view = {k.key: k.in_view for k in before}
    for d in rest:
        assert d.explanation == (DISAPPEAR if in_view[d.key] else HIDDEN)
    for d in decisions[:len(now)]:
        assert sum(a.probability for a in d.alternatives) == pytest.approx(1.0)
        assert 0.0 <= d.probability <= 1.0
        if d.object is None:
            assert d.explanation == APPEAR
        elif not in_view[d.object]:
            assert d.explanation == MOVE  # formula 6: out of view, only a move


def test_the_calibration_learns_what_similar_means_for_the_sensors():
    """Colour histograms of different objects are rather alike by the Bhattacharyya
    coefficient (about 0.75): the prior, made for similarities that fall to 0 for different
    objects, takes two of them for one. After some scenes of objects that stayed, the model
    has learnt both distributions: the same object seen again still counts as the same, two
    different ones no longer do. The calibration survives a round trip through its document."""
    rng = np.random.default_rng(7)
    looks = [rng.dirichlet(np.ones(16)) for _ in range(4)]
    places = [(0.3 * k, 0.0) for k in range(4)]

    def seen(k: int, scene: int) -> Observation:
        noisy = np.clip(looks[k] + rng.normal(0, 0.01, 16), 0, None)
        x, y = places[k] + rng.normal(0, 0.005, 2)
        return obs(f"{scene}-{k}", x, y, [ColorHistogram(histogram=noisy / noisy.sum())])

    def similarity(a: int, b: int) -> float:
        return appearance(seen(a, 0).evidence, seen(b, 0).evidence, DEFAULTS.evidence_floor)

    same = float(np.median([similarity(k, k) for k in range(4) for _ in range(25)]))
    different = float(np.median([similarity(a, b) for a in range(4) for b in range(a)]))
    calibration = Calibration.prior(DEFAULTS)
    assert calibration.look.odds(different) > 1

    belief = [Known(k, seen(k, 0), in_view=True) for k in range(4)]
    for scene in range(1, 40):
        now = [seen(k, scene) for k in range(4)]
        resolve(now, belief, DEFAULTS, calibration)
        belief = [Known(k, o, in_view=True) for k, o in enumerate(now)]

    assert calibration.look.odds(same) > 3
    assert calibration.look.odds(different) < 0.05
    assert Calibration.from_document(calibration.to_document()) == calibration


def test_of_two_lookalikes_the_one_seen_last_with_that_look_is_the_one_moved_here():
    """An object that took a cup's look once (a wrong link) and was seen since as the plate it
    is, is not where the cup went: the object seen last *with the look* is (Known.others_seen),
    not the object seen last."""
    took = Known("took", obs("its-plate", 0.0, 0.0, plate()), False,
                 [obs("a-cup-once", 1.0, 0.0, cup())], last_seen=10, others_seen=[3])
    mug = Known("cup", obs("the-cup", 3.0, 0.0, cup()), False, last_seen=5)
    now = [obs("n", 6.0, 0.0, cup())]
    assert outcome(resolve(now, [took, mug], DEFAULTS))["n"] == ("cup", MOVE)
    took = replace(took, others_seen=[7])  # had it been seen with it after the cup
    assert outcome(resolve(now, [took, mug], DEFAULTS))["n"] == ("took", MOVE)


def test_a_place_long_unseen_is_weak_evidence_of_the_object_there():
    """Something showing a cup's look where a plate was seen: just after, the plate turned
    is likelier than the cup moved there; ten hours later (the prior dwell is an hour) the
    plate has likely gone long ago, and the cup, which looks the same, is the one."""
    plate_there = Known("plate", obs("old-plate", 0.0, 0.0, plate()), True, last_seen=0)
    mug = Known("cup", obs("old-cup", 3.0, 0.0, cup()), False, last_seen=0)
    now = [obs("n", 0.0, 0.0, cup())]
    hour = 3600 * 10**9
    assert outcome(resolve(now, [plate_there, mug], DEFAULTS, now=1))["n"] == (
        "plate", NEWVIEW)
    assert outcome(resolve(now, [plate_there, mug], DEFAULTS, now=10 * hour))["n"] == (
        "cup", MOVE)


def blob(centre: float) -> ColorHistogram:
    """A hue histogram: one colour, spread as a camera's pixels are."""
    bins = (np.arange(32) + 0.5) / 32
    values = np.exp(-0.5 * ((bins - centre) / 0.08) ** 2) + 1e-3
    return ColorHistogram(histogram=values / values.sum(), space="H")


def early_calibration() -> Calibration:
    """What the model learns in a robot's first scenes: three objects on a table, colours far
    apart (hues 0.1, 0.45, 0.8), seen seven times with noise 0.01."""
    rng = np.random.default_rng(5)
    colours = [0.1, 0.45, 0.8]
    calibration = Calibration.prior(DEFAULTS)
    belief = [Known(k, obs(f"0-{k}", 0.3 * k, 0.0, [blob(c)]), True)
              for k, c in enumerate(colours)]
    for scene in range(1, 8):
        now = [obs(f"{scene}-{k}", 0.3 * k + rng.normal(0, 0.01), rng.normal(0, 0.01),
                   [blob(c + rng.normal(0, 0.01))]) for k, c in enumerate(colours)]
        resolve(now, belief, DEFAULTS, calibration)
        belief = [Known(k, o, True) for k, o in enumerate(now)]
    return calibration


def test_a_new_object_is_not_taken_for_a_hidden_one_it_merely_resembles():
    """Early in a robot's life the model has seen few pairs of different objects, none
    nearly alike: how rarely two different ones look this near alike, it cannot yet say (the
    lower tail of Histogram). A new object whose colour lies six times the sensor's noise
    from a hidden object's is a new object, not that one moved (it was ~1,000 times likelier
    that one while the odds dropped to a floor below the pairs seen); the hidden object
    itself, moved here, is still recognised."""
    calibration = early_calibration()
    hidden = Known("cup", obs("cup-then", 5.0, 0.0, [blob(0.62)]), in_view=False)
    near_alike = [obs("new", 9.0, 0.0, [blob(0.62 + 0.06)])]
    assert outcome(resolve(near_alike, [hidden], DEFAULTS, calibration))["new"] == (
        None, APPEAR)
    moved = [obs("moved", 9.0, 0.0, [blob(0.62 + 0.01)])]
    assert outcome(resolve(moved, [hidden], DEFAULTS, calibration))["moved"] == (
        "cup", MOVE)


def test_a_lookalike_is_one_that_looks_as_alike_as_the_object_itself():
    """A cup seen where it stood looks beyond doubt like another object not in view with the
    very same look (the cup remembered twice: consolidation merges the two), and beyond
    doubt, but far less, like a bowl of a near colour: that one is another object, not a
    lookalike (taking it for one merged distinct objects of a crowded world)."""
    calibration = early_calibration()
    cup = Known("cup", obs("cup-then", 0.0, 0.0, [blob(0.62)]), in_view=True)
    twin = Known("twin", obs("twin-then", 6.0, 0.0, [blob(0.62)]), in_view=False)
    bowl = Known("bowl", obs("bowl-then", 9.0, 0.0, [blob(0.64)]), in_view=False)
    now = [obs("now", 0.0, 0.0, [blob(0.62)])]
    odds = [float(calibration.look.odds(appearance(now[0].evidence, k.last.evidence,
                                                   DEFAULTS.evidence_floor)))
            for k in (twin, bowl)]
    assert odds[1] >= DEFAULTS.lookalike_odds and odds[1] * DEFAULTS.superseded < odds[0]
    decision = resolve(now, [cup, twin, bowl], DEFAULTS, calibration)[0]
    assert (decision.object, decision.explanation) == ("cup", STAY)
    assert set(decision.lookalikes) == {"twin"}


def test_the_dwell_time_is_learnt_from_the_places_looked_at():
    """Objects found gone from their place one look in five, 10 s after they were last seen:
    an object stays about 50 s (the prior said an hour, now forgotten)."""
    dwell = Calibration.prior(DEFAULTS).dwell
    assert dwell.staying(60.0) > 0.98
    for k in range(400):
        dwell.learn(k % 5 == 0, 10.0, DEFAULTS.memory)
    assert dwell.staying(50.0) == pytest.approx(np.exp(-1), rel=0.1)


def test_a_neighbours_place_is_not_taken_for_the_same_place():
    """How near another object lies is learnt with its lower tail: on tables of objects 0.15-
    0.3 m apart, 3 m from each other, positions good to 2.5 cm, two observations 0.12 m apart
    are likelier two objects than one, however far most other objects lie (a spread fitted
    to the bulk of the distances, metres, made them e^12 times likelier one object: a thing
    put beside another's old spot was taken for that one, turned). The same spot still is."""
    rng = np.random.default_rng(3)
    tables = [np.array([3.0 * t, 0.0]) for t in range(4)]
    places = [table + (0.15 * (k % 3), 0.2 * (k // 3)) for table in tables for k in range(6)]
    calibration = Calibration.prior(DEFAULTS)
    belief = [Known(k, obs(f"0-{k}", *p, []), in_view=True) for k, p in enumerate(places)]
    for scene in range(1, 30):
        table = scene % 4
        now = [obs(f"{scene}-{k}", *(places[k] + rng.normal(0, 0.025, 2)), [])
               for k in range(6 * table, 6 * table + 6)]
        for known_one in belief:
            known_one.in_view = 6 * table <= known_one.key < 6 * table + 6
        resolve(now, belief, DEFAULTS, calibration)
        for k, seen in zip(range(6 * table, 6 * table + 6), now, strict=True):
            belief[k] = Known(k, seen, in_view=True)

    def place_odds(metres: float) -> float:
        return calibration.place.odds(np.exp(-(metres / (2 * DEFAULTS.proximity_sigma)) ** 2))

    assert place_odds(0.12) < 1
    assert place_odds(0.02) > 100


def test_a_calibration_stored_by_an_older_release_still_loads():
    """One stored when the place of different objects was a Gamma spread, and before the
    dwell time was learnt: what it learnt in the old form starts from the prior."""
    prior = Calibration.prior(DEFAULTS)
    document = prior.to_document()
    document["place"]["different"] = {"weight": 12.0, "mean": 40.0, "variance": 900.0}
    del document["dwell"]
    assert Calibration.from_document(document) == prior
