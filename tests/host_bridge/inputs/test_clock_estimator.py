"""The relay clock estimator (host_bridge/inputs/clocks.py) on synthetic round trips whose truth
is known: the relay's clock is the PC's plus an offset (drifting, stepping), each way takes its
own delay."""

from __future__ import annotations

import itertools
import random

import pytest

from host_bridge.inputs.clocks import (
    MAX_DRIFT,
    SLEW,
    ClockEstimate,
    ClockEstimator,
    ClockSample,
    Correction,
)

START_NS = 1_700_000_000 * 10**9
MS = 1_000_000
OFFSET_NS = 7_500 * MS
HOURS_NS = 2 * 3600 * 10**9


def round_trip(
    sent_ns: int, offset_ns: int, out_ns: int, back_ns: int, relay_ns: int = 20_000
) -> ClockSample:
    """A query sent at ``sent_ns`` (PC clock) to a relay whose clock is ``offset_ns`` ahead,
    ``out_ns`` on the way there, ``relay_ns`` in the relay, ``back_ns`` on the way back."""
    arrived = sent_ns + out_ns
    replied = arrived + relay_ns
    return ClockSample(sent_ns, arrived + offset_ns, replied + offset_ns, replied + back_ns)


def test_even_delays_give_the_offset_exactly_and_half_the_round_trip_as_uncertainty() -> None:
    sample = round_trip(START_NS, OFFSET_NS, out_ns=MS, back_ns=MS)
    assert sample.offset_ns == OFFSET_NS
    assert sample.round_trip_ns == 2 * MS
    estimate = ClockEstimator().add(sample)
    assert estimate == ClockEstimate(OFFSET_NS, MS, sample.answered_ns, jumped=False)


def test_the_shortest_round_trip_wins_over_asymmetric_ones() -> None:
    # A link whose way back is congested (5-40 ms) but once: out 0.2 ms, back 0.3 ms.
    estimator = ClockEstimator()
    sent = START_NS
    for back_ms in (5, 12, 40, 0.3, 9, 25, 7, 18):
        sample = round_trip(sent, OFFSET_NS, out_ns=200_000, back_ns=int(back_ms * MS))
        estimate = estimator.add(sample)
        assert estimate is not None
        # Whatever the asymmetry, the truth lies within the bound.
        assert abs(estimate.offset_ns - OFFSET_NS) <= estimate.uncertainty_ns
        sent += 10 * MS
    assert estimate is not None
    # The 0.2/0.3 ms sample: off by half the asymmetry, 0.05 ms; bound its half round trip.
    assert estimate.offset_ns == OFFSET_NS - 50_000
    # Half its round trip, 0.25 ms, and 100 ppm of the 58 ms since.
    assert estimate.uncertainty_ns == pytest.approx(255_800, abs=100)


def test_random_delays_never_put_the_truth_outside_the_uncertainty() -> None:
    rng = random.Random(24)
    estimator = ClockEstimator()
    sent = START_NS
    for _ in range(500):
        out = int(rng.expovariate(1 / (3 * MS))) + 100_000
        back = int(rng.expovariate(1 / (20 * MS))) + 100_000
        estimate = estimator.add(round_trip(sent, -OFFSET_NS, out, back, relay_ns=rng.randrange(10**6)))
        assert estimate is not None
        assert not estimate.jumped
        assert abs(estimate.offset_ns + OFFSET_NS) <= estimate.uncertainty_ns
        sent += 2_000 * MS
    assert estimate is not None
    assert estimate.uncertainty_ns < 5 * MS


def test_drift_is_followed() -> None:
    # The relay's crystal runs 60 ppm fast: over 10 minutes its clock gains 36 ms.
    drift = 60e-6
    estimator = ClockEstimator()
    errors = []
    for i in range(300):
        sent = START_NS + i * 2_000 * MS
        truth = OFFSET_NS + round(drift * (sent - START_NS))
        delay = 400_000 + (i % 7) * 300_000  # even each way: what is off is the drift's
        estimate = estimator.add(round_trip(sent, truth, out_ns=delay, back_ns=delay))
        assert estimate is not None
        assert abs(estimate.offset_ns - truth) <= estimate.uncertainty_ns
        errors.append(abs(estimate.offset_ns - truth))
    assert drift < MAX_DRIFT
    assert round(drift * 598e9) > 35 * MS  # gained over the run
    # Fresh samples win as the older ones age: the error stays the drift over a few samples.
    assert max(errors) < 1.2 * MS


def test_a_step_of_the_clock_restarts_the_window_from_the_first_sample_after_it() -> None:
    estimator = ClockEstimator()
    sent = START_NS
    for _ in range(10):  # a Pi booted with the time it last shut down: 2 h behind
        estimator.add(round_trip(sent, -2 * 3600 * 10**9, out_ns=100_000, back_ns=100_000))
        sent += 2_000 * MS
    # NTP reaches it and steps its clock to the truth, 7.5 s ahead of a PC that has no NTP.
    estimate = estimator.add(round_trip(sent, OFFSET_NS, out_ns=3 * MS, back_ns=MS))
    assert estimate is not None
    assert estimate.jumped
    assert estimate.offset_ns == OFFSET_NS + MS  # from that one sample: (3 - 1) / 2 ms off
    assert estimate.uncertainty_ns == 2 * MS
    # The older samples are gone: better ones after it refine it, none before it returns.
    estimate = estimator.add(round_trip(sent + 10 * MS, OFFSET_NS, out_ns=100_000, back_ns=100_000))
    assert estimate is not None
    assert not estimate.jumped
    assert estimate.offset_ns == OFFSET_NS
    assert estimate.uncertainty_ns == 100_000


def test_a_step_within_the_bounds_is_no_jump() -> None:
    estimator = ClockEstimator()
    estimator.add(round_trip(START_NS, OFFSET_NS, out_ns=5 * MS, back_ns=5 * MS))
    estimate = estimator.add(round_trip(START_NS + 10 * MS, OFFSET_NS + 2 * MS, 5 * MS, 5 * MS))
    assert estimate is not None
    assert not estimate.jumped


def test_a_round_trip_a_step_made_negative_is_ignored() -> None:
    estimator = ClockEstimator()
    first = estimator.add(round_trip(START_NS, OFFSET_NS, MS, MS))
    # The relay's clock stepped 1 s ahead between receiving and replying.
    stepped = ClockSample(START_NS + 10 * MS, START_NS + 11 * MS + OFFSET_NS,
                          START_NS + 11 * MS + OFFSET_NS + 10**9, START_NS + 12 * MS)
    assert stepped.round_trip_ns < 0
    assert estimator.add(stepped) is None
    assert estimator.estimate == first


def corrected(correction: Correction, relay_ns: list[int]) -> list[int]:
    return [t - correction.offset_ns(t) for t in relay_ns]


def test_a_refined_estimate_that_moves_times_back_is_slewed_to_in_order() -> None:
    # The bad-link test's run: a first burst over a congested link gave -320 ms ±421 ms, a
    # later round trip 0 ±100 ms; stepping put a 30 Hz topic's next messages before its last.
    coarse = ClockEstimate(-320 * MS, 421 * MS, START_NS)
    refined = ClockEstimate(0, 100 * MS, START_NS + 2000 * MS)
    correction = Correction.at_once(coarse).then(refined)
    period = 33 * MS
    relay_ns = [START_NS + 1000 * MS + i * period for i in range(100)]  # the relay's clock: the PC's
    times = corrected(correction, relay_ns)
    assert all(b > a for a, b in itertools.pairwise(times))
    # Before the refined estimate came: the old correction; 640 ms after it: the new one.
    assert times[0] == relay_ns[0] + 320 * MS
    assert correction.offset_ns(refined.at_ns) == -320 * MS
    settled = refined.at_ns + int(320 * MS / SLEW)
    assert correction.offset_ns(settled - 10 * MS) < 0
    assert correction.offset_ns(settled) == 0
    assert correction.offset_ns(settled + 10**9) == 0


def test_a_correction_that_moves_times_later_or_follows_a_step_applies_at_once() -> None:
    old = Correction.at_once(ClockEstimate(0, 100 * MS, START_NS))
    later = old.then(ClockEstimate(-300 * MS, MS, START_NS + 1000 * MS))
    assert later.offset_ns(START_NS + 1000 * MS) == -300 * MS
    # The relay's clock stepped two hours ahead: followed at once (jumped), not over four hours.
    stepped = old.then(ClockEstimate(HOURS_NS, MS, START_NS + 1000 * MS, jumped=True))
    assert stepped.offset_ns(START_NS + 1000 * MS + HOURS_NS) == HOURS_NS


def test_an_estimate_during_a_slew_continues_from_where_the_slew_is() -> None:
    correction = Correction.at_once(ClockEstimate(-400 * MS, 400 * MS, START_NS)).then(
        ClockEstimate(0, 200 * MS, START_NS + 1000 * MS))
    midway = START_NS + 1400 * MS  # the relay's clock 400 ms into the slew: half of it made
    assert correction.offset_ns(midway) == -200 * MS
    # A third estimate, -100 ms, comes then (the relay's clock: its time plus the offset).
    again = correction.then(ClockEstimate(-100 * MS, 100 * MS, midway + 100 * MS))
    assert again.offset_ns(midway - 50 * MS) == -200 * MS
    assert again.offset_ns(midway + 100 * MS) == -200 * MS + int(SLEW * 100 * MS)
    assert again.offset_ns(midway + 10**9) == -100 * MS
