"""Parked cars in rows along the kerbs: parallel either way round, angled and perpendicular bays.

Road frame: ``s`` along the centre line, ``n`` to the left; side ``-1`` is the ego's (right-hand
traffic runs along +s there), side ``+1`` the oncoming one (traffic along -s). A car's heading is
written in the side's (along, towards-kerb) frame: parallel cars point along the road (with or
against their side's traffic), bay cars along ``(lean * cos a, sin a)`` (nose to the kerb) or the
opposite (tail to the kerb), where ``lean`` = +-1 says which way along the road a segment's bays
lean. A car's kerb-side end stands ``kerb_gap`` from the kerb; neighbours in a row stand
``gap`` apart, footprint to footprint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import PARKING_LAYOUTS, ParkingConfig, SynthConfig
from .vehicles import VehicleDeck
from .world import Centreline, SynthCar, collides


#: Cosines / sines below this count as zero (parallel or perpendicular bays).
NEGLIGIBLE = 1e-6


@dataclass(frozen=True)
class ParkingSegment:
    """A stretch of one side of the street with one parking layout."""

    side: int  # -1 right (the ego's side), +1 left
    s0: float
    s1: float
    layout: str  # one of PARKING_LAYOUTS
    #: Bay angle to the road in degrees (0 parallel, 90 perpendicular).
    angle_deg: float
    #: +1: noses to the kerb point along +s; -1: along -s (angled bays only).
    lean: int


def strip_depth(segment: ParkingSegment, cfg: ParkingConfig) -> float:
    """Depth of the parking strip (across the road) that a segment's layout needs."""
    if segment.layout == "parallel":
        return cfg.parallel_depth
    a = np.deg2rad(segment.angle_deg)
    return float(cfg.bay_length * np.sin(a) + cfg.bay_width * np.cos(a))


def draw_segments(rng: np.random.Generator, cfg: ParkingConfig, s0: float, s1: float
                  ) -> list[ParkingSegment]:
    """Cut both sides of ``[s0, s1]`` into segments of random layouts."""
    names = [name for name, _ in cfg.layouts]
    unknown = set(names) - set(PARKING_LAYOUTS)
    if unknown:
        raise ValueError(f"ParkingConfig.layouts: unknown layout(s) {sorted(unknown)} "
                         f"(known: {', '.join(PARKING_LAYOUTS)})")
    p = np.array([w for _, w in cfg.layouts], dtype=np.float64)
    if np.any(p < 0) or p.sum() <= 0:
        raise ValueError("ParkingConfig.layouts: weights must be non-negative, not all zero")
    segments = []
    for side in (-1, 1):
        start = s0
        while start < s1:
            end = min(start + float(rng.uniform(*cfg.segment_length)), s1)
            layout = names[int(rng.choice(len(names), p=p / p.sum()))]
            angle = {"parallel": 0.0, "perpendicular": 90.0}.get(layout)
            if angle is None:
                angle = float(rng.uniform(*cfg.angle_deg))
            segments.append(ParkingSegment(side, start, end, layout, angle,
                                           1 if rng.uniform() < 0.5 else -1))
            start = end
    return segments


def strip_widths(segments: list[ParkingSegment], cfg: ParkingConfig) -> tuple[float, float]:
    """Parking strip width of the (right, left) side: the deepest of its segments."""
    def side_width(side: int) -> float:
        return max([strip_depth(g, cfg) for g in segments if g.side == side],
                   default=cfg.parallel_depth)
    return side_width(-1), side_width(1)


def _heading(rng: np.random.Generator, segment: ParkingSegment, cfg: ParkingConfig
             ) -> tuple[float, float, str]:
    """A car's heading in the side's (along, towards-kerb) frame and its parking label."""
    jitter = np.deg2rad(rng.normal(0.0, cfg.yaw_jitter_deg))
    if segment.layout == "parallel":
        traffic = -float(segment.side)  # right side: +s, left side: -s
        reverse = rng.uniform() < cfg.parallel_reverse_prob
        along = traffic * (-1.0 if reverse else 1.0)
        return along * np.cos(jitter), np.sin(jitter), ("parallel_reversed" if reverse
                                                         else "parallel")
    a = np.deg2rad(segment.angle_deg) + jitter
    sign = -1.0 if rng.uniform() < cfg.bay_reverse_prob else 1.0
    return sign * segment.lean * np.cos(a), sign * np.sin(a), segment.layout


def _spacing(prev: SynthCar, length: float, width: float, angle_deg: float, gap: float) -> float:
    """Centre-to-centre distance along the road of two equal-angle neighbours ``gap`` apart."""
    a = np.deg2rad(angle_deg)
    lengths = 0.5 * (prev.size_lwh[0] + length) + gap
    widths = 0.5 * (prev.size_lwh[1] + width) + gap
    along = lengths / np.cos(a) if np.cos(a) > NEGLIGIBLE else np.inf
    across = widths / np.sin(a) if np.sin(a) > NEGLIGIBLE else np.inf
    return float(min(along, across))


def place_rows(rng: np.random.Generator, config: SynthConfig, cl: Centreline,
               segments: list[ParkingSegment], edges: tuple[float, float], deck: VehicleDeck,
               placed: list[SynthCar], n_frames: int, first_id: int) -> list[SynthCar]:
    """Fill every segment with a row of parked cars; returns them in order along each side.

    ``edges`` = (right, left) kerb offsets; ``placed`` are the cars already in the street (moving
    ones included, avoided at every frame). Instance ids count up from ``first_id``.
    """
    cfg = config.parking
    out: list[SynthCar] = []
    for side in (-1, 1):
        edge = edges[0] if side < 0 else edges[1]
        free = -np.inf  # the row is free from here on (along s)
        for seg in [g for g in segments if g.side == side]:
            free, prev = max(free, seg.s0), None
            while free < seg.s1:
                if rng.uniform() < cfg.hole_prob:
                    free, prev = free + float(rng.uniform(*cfg.hole_length)), None
                    continue
                slot = _fill_slot(rng, config, cl, seg, side, edge, deck, free, prev,
                                  placed + out, n_frames, first_id + len(out))
                if slot is None:
                    free, prev = free + float(rng.uniform(*cfg.hole_length)), None
                    continue
                car, s_car, along = slot
                if s_car + 0.5 * along > seg.s1:
                    deck.put_back(car.model.vehicle_class or car.model.name)
                    break
                out.append(car)
                free, prev = s_car + 0.5 * along, (car, s_car)
    return out


def _fill_slot(rng: np.random.Generator, config: SynthConfig, cl: Centreline,
               seg: ParkingSegment, side: int, edge: float, deck: VehicleDeck, free: float,
               prev: tuple[SynthCar, float] | None, placed: list[SynthCar], n_frames: int,
               instance_id: int) -> tuple[SynthCar, float, float] | None:
    """The next car of a row: ``gap`` after ``prev`` = (car, its s), or after ``free`` when the
    row starts. Returns the car, its s and its extent along the road, or None (slot given up)."""
    cfg, road = config.parking, config.road
    lane_limit = road.lane_width - cfg.lane_intrusion
    for _ in range(cfg.max_models):
        name, model = deck.draw()
        length, width = float(model.size[0]), float(model.size[1])
        h_along, h_kerb, label = _heading(rng, seg, cfg)
        rel = np.arctan2(h_kerb, h_along)  # heading angle from the side's along axis
        across = length * abs(np.sin(rel)) + width * abs(np.cos(rel))
        along = length * abs(np.cos(rel)) + width * abs(np.sin(rel))
        n_abs = edge - float(rng.uniform(*cfg.kerb_gap)) - 0.5 * across
        if n_abs - 0.5 * across < lane_limit:
            deck.put_back(name)
            continue
        gap = float(rng.uniform(*cfg.gap))
        s = free + gap + 0.5 * along if prev is None else \
            prev[1] + _spacing(prev[0], length, width, seg.angle_deg, gap)
        for _move in range(cfg.max_moves):
            car = _parked_car(rng, config, cl, model, side, s, n_abs, h_along, h_kerb, label,
                              instance_id)
            near = prev is not None and car.footprint(0).distance(prev[0].footprint(0)) < gap
            if not near and not collides(car, placed, n_frames, cfg.min_clearance):
                return car, s, along
            s += cfg.retry_step
        deck.put_back(name)
        return None
    return None


def _parked_car(rng: np.random.Generator, config: SynthConfig, cl: Centreline, model,
                side: int, s: float, n_abs: float, h_along: float, h_kerb: float, label: str,
                instance_id: int) -> SynthCar:
    """A parked car centred at road coordinates ``(s, side * n_abs)`` with the given heading."""
    psi = float(cl.heading(s))
    t = np.array([np.cos(psi), np.sin(psi)])
    kerb = side * np.array([-np.sin(psi), np.cos(psi)])
    h = h_along * t + h_kerb * kerb
    xy = cl.at(s, side * n_abs)
    pal = config.texture.car_palette
    return SynthCar(instance_id, model, False, float(np.arctan2(h[1], h[0])),
                    np.array([xy[0], xy[1], 0.5 * model.size[2]]), np.zeros(3),
                    pal[int(rng.integers(len(pal)))], int(rng.integers(1 << 30)), parking=label)


__all__ = ["ParkingSegment", "draw_segments", "place_rows", "strip_depth", "strip_widths"]
