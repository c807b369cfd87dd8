"""Random routes: rides nobody tuned on, drawn from a route number.

The eight scenarios are what the estimator was tuned and measured on. A route is a 100 s ride laid out from
segments drawn at random from its number: straights, speed changes (20-125 km/h), curves and turns of either
hand up to ~5.5 m/s^2 (scaled by the road's friction, 0.6-1.0), weaves, stops, braking inside a curve. Route N is
the same ride everywhere (``route_scenario(N)``; the simulator's scenario ``route_N``). The simulated rider may
fall on the tightest draws (a few in a hundred): the ride is scored up to the fall, as every scenario's is.
"""

from __future__ import annotations

import numpy as np

from ptw_rt.sim.scenarios import Plan, Scenario, Seg, plan_from_segments, turn

ROUTE_PREFIX = "route_"
MAX_ROUTE = 10**9
ROUTE_DURATION = 100.0  # s
# segment kinds and their odds
KINDS = ("straight", "speed", "curve", "turn", "weave", "stop", "brake_in_curve")
ODDS = (0.15, 0.20, 0.20, 0.15, 0.12, 0.06, 0.12)
MIN_KMH, MAX_KMH = 20.0, 125.0
MU_RANGE = (0.6, 1.0)
MAX_LATERAL = 5.5  # m/s^2 at friction 1, scaled by the route's friction


def route_segments(route: int) -> tuple[list[Seg], float, float]:
    """(segments, friction, initial speed in km/h) of route `route`, enough for ROUTE_DURATION."""
    rng = np.random.default_rng(10_000 + route)
    mu = float(rng.uniform(*MU_RANGE))
    kmh = float(rng.choice([0.0, 20.0, 40.0, 60.0]))
    start = kmh
    segs = [Seg(3.0, kmh)] if kmh > 0 else [Seg(2.0, 0.0), Seg(6.0, 40.0)]
    kmh = kmh or 40.0
    t = sum(s.duration for s in segs)
    while t < ROUTE_DURATION:
        kind = str(rng.choice(KINDS, p=ODDS))
        side = float(rng.choice([-1.0, 1.0]))
        if kind == "stop":
            segs += [Seg(float(rng.uniform(3, 8)), 0.0), Seg(float(rng.uniform(1, 5)), 0.0)]
            kmh = 0.0
        elif kind == "speed" or kmh < 15.0:  # after a stop, pull away first
            kmh = float(rng.uniform(MIN_KMH, MAX_KMH))
            segs.append(Seg(float(rng.uniform(3, 10)), kmh))
        elif kind == "straight":
            segs.append(Seg(float(rng.uniform(2, 8)), kmh))
        elif kind == "curve":
            lat = side * float(rng.uniform(0.5, MAX_LATERAL * mu))
            segs += [
                Seg(float(rng.uniform(3, 10)), kmh, lat, float(rng.uniform(0.8, 2.5))),
                Seg(float(rng.uniform(1, 2)), kmh, 0.0, 1.2),
            ]
        elif kind == "turn" and kmh <= 60.0:
            segs += turn(side * float(rng.uniform(30, 120)), kmh, float(rng.uniform(1.0, 3.5 * mu)))
        elif kind == "weave":
            lat, period = float(rng.uniform(1.0, 4.0 * mu)), float(rng.uniform(1.0, 3.0))
            for k in range(int(rng.integers(2, 6))):
                segs.append(Seg(period / 2, kmh, lat if k % 2 == 0 else -lat, period / 2))
            segs.append(Seg(1.5, kmh, 0.0, 1.0))
        else:  # braking inside a curve (or a turn too fast to take: a curve braked into)
            lat = side * float(rng.uniform(1.0, 4.0 * mu))
            slower = max(kmh * float(rng.uniform(0.4, 0.8)), MIN_KMH)
            segs += [
                Seg(2.0, kmh, lat, 1.5),
                Seg(float(rng.uniform(2, 5)), slower, lat, 0.1),
                Seg(1.5, slower, 0.0, 1.2),
            ]
            kmh = slower
        t = sum(s.duration for s in segs)
    return segs, mu, start


def route_scenario(route: int) -> Scenario:
    """The simulator's scenario ``route_N`` (0 <= N < MAX_ROUTE)."""
    if not 0 <= route < MAX_ROUTE:
        raise ValueError(f"route number {route} outside 0..{MAX_ROUTE - 1}")
    segs, mu, start = route_segments(route)

    def build(duration: float) -> Plan:
        return plan_from_segments(segs, duration, start, heading0_deg=0.0, mu=mu)

    return Scenario(
        f"{ROUTE_PREFIX}{route}",
        f"random route {route}: {len(segs)} segments, friction {mu:.2f}, from {start:.0f} km/h",
        ROUTE_DURATION,
        20_000 + route % 1_000_000,
        build,
        # log time stamps apart from the eight scenarios' (0-7000 s) and from each other's (within a day's seconds)
        10_000.0 + 200.0 * (route % 400),
    )
