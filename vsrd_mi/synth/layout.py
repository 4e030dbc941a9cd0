"""Lay out a synthetic sequence: the street, the ego's track, the cars and the props.

:func:`build_world` draws everything from ``(seed, seq)``. The draws of the original generator
(ego track, street, buildings, scattered parked cars, basic procedural cars) come from one
stream in a fixed order, so their worlds stay the same; each newer feature draws from a stream of
its own (:data:`STREAM_PARKING` ...), so switching one on leaves the others' draws alone.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..data.kitti360 import sequence_name
from ..data.labels import INSTANCE_FACTOR
from .cars import CarModel, bundled_mesh_paths, load_car_mesh, procedural_car, scaled
from .config import SynthConfig
from .parking import draw_segments, place_rows, strip_widths
from .props import place_props
from .vehicles import VehicleDeck
from .world import (Centreline, PlacementError, Rig, SynthCar, SynthWorld, build_static,
                    camera_pitch_roll, collides, ego_poses, ego_track, make_rig, road_edges,
                    vehicle_attitude_for, vehicle_pose)

#: Random streams of the newer features (``default_rng([seed, seq, stream])``).
STREAM_PARKING, STREAM_VEHICLES, STREAM_PROPS, STREAM_CAMERA, STREAM_TRAFFIC = 1, 2, 3, 4, 5


def _pick_model(rng: np.random.Generator, config: SynthConfig,
                meshes: Sequence[CarModel]) -> CarModel:
    if not meshes or rng.uniform() < config.traffic.procedural_fraction:
        return procedural_car(rng, config.procedural)
    model = meshes[int(rng.integers(len(meshes)))]
    j = config.traffic.mesh_scale_jitter
    return scaled(model, 1.0 + float(rng.uniform(-j, j)))


def _paint(rng: np.random.Generator, config: SynthConfig) -> tuple[int, int, int]:
    pal = config.texture.car_palette
    return pal[int(rng.integers(len(pal)))]


def place_dynamic(rng: np.random.Generator, config: SynthConfig, cl: Centreline,
                  ego_s: np.ndarray, model: CarModel, instance_id: int) -> SynthCar:
    """A car driving straight at constant speed along the chord of its lane (ego lane ahead of
    the ego, or the oncoming lane passing the ego)."""
    tr, n = config.traffic, len(ego_s)
    v = float(rng.uniform(*tr.speed)) / config.rig.frame_rate
    length = float(model.size[0])
    k = np.arange(n)
    if rng.uniform() < tr.same_direction_prob:
        lane, sign = -0.5 * config.road.lane_width, 1.0
        s0 = float(np.max(ego_s - v * k)) + tr.follow_gap + 0.5 * length + rng.uniform(*tr.follow_extra)
    else:
        lane, sign = 0.5 * config.road.lane_width, -1.0
        kp = rng.uniform(*tr.oncoming_pass) * n
        s0 = float(np.interp(kp, k, ego_s, right=ego_s[-1] + config.ego.step * (kp - n + 1))) + v * kp
    s_end = s0 + sign * v * max(n - 1, 1)
    a, b = cl.at(s0, lane), cl.at(s_end, lane)
    vel_xy = (b - a) / max(n - 1, 1)
    yaw = float(np.arctan2(vel_xy[1], vel_xy[0]))
    centre0 = np.array([a[0], a[1], 0.5 * model.size[2]])
    return SynthCar(instance_id, model, True, yaw, centre0, np.array([vel_xy[0], vel_xy[1], 0.0]),
                    _paint(rng, config), int(rng.integers(1 << 30)))


def place_scattered(rng: np.random.Generator, config: SynthConfig, cl: Centreline,
                    ego_s: np.ndarray, model: CarModel, instance_id: int) -> SynthCar | None:
    """A parked car at a random spot of a parallel parking strip (None when its rotated
    footprint does not fit)."""
    tr, road = config.traffic, config.road
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    s = float(rng.uniform(ego_s[0] + tr.parked_range[0], ego_s[-1] + tr.parked_range[1]))
    rel = np.deg2rad(rng.normal(0.0, tr.parked_yaw_jitter_deg))
    angled = rng.uniform() < tr.angled_prob
    if angled:
        rel += np.deg2rad(rng.uniform(*tr.angled_yaw_deg)) * (1.0 if rng.uniform() < 0.5 else -1.0)
    reverse = rng.uniform() < tr.parked_reverse_prob
    if reverse:
        rel += np.pi
    # lateral half-extent of the rotated footprint, across the road
    l, w = float(model.size[0]), float(model.size[1])
    half_across = 0.5 * (l * abs(np.sin(rel)) + w * abs(np.cos(rel)))
    inner = road.lane_width - tr.lane_intrusion + half_across
    outer = road.lane_width + road.parking_width - tr.kerb_clearance - half_across
    if inner > outer:
        return None
    mid = road.lane_width + 0.5 * road.parking_width + rng.uniform(-1, 1) * tr.parked_lateral_jitter
    n = side * float(np.clip(mid, inner, outer))
    xy = cl.at(s, n)
    yaw = float(cl.heading(s)) + rel
    # a car that is not turned round faces +s, the traffic direction of the right side (n < 0)
    label = "angled" if angled else ("parallel" if reverse == (side > 0) else "parallel_reversed")
    return SynthCar(instance_id, model, False, yaw, np.array([xy[0], xy[1], 0.5 * model.size[2]]),
                    np.zeros(3), _paint(rng, config), int(rng.integers(1 << 30)), parking=label)


def build_world(seq: int = 0, frames: int = 60, n_static: int = 4, n_dynamic: int = 2,
                seed: int = 0, meshes: Sequence[str | Path] | None = None,
                config: SynthConfig = SynthConfig()) -> SynthWorld:
    """Lay out a synthetic sequence (deterministic in all arguments).

    ``meshes``: car mesh files (None: the bundled CC0 meshes; empty: procedural cars only).
    With ``config.traffic.parking == "rows"``, ``n_static`` is the most parked cars kept (the
    rows are filled, then the cars nearest the start of the street kept). Raises
    :class:`PlacementError` when the cars cannot be placed without collisions and
    :class:`~vsrd_mi.errors.DataError` for unreadable mesh files.
    """
    if frames < 1 or n_static < 0 or n_dynamic < 0 or seq < 0:
        raise ValueError(f"need frames >= 1, seq >= 0 and non-negative car counts "
                         f"(got frames={frames}, seq={seq}, static={n_static}, dynamic={n_dynamic})")
    if n_static + n_dynamic >= INSTANCE_FACTOR:
        raise ValueError(f"at most {INSTANCE_FACTOR - 1} cars fit the KITTI-360 instance encoding")
    if config.traffic.parking not in ("scatter", "rows"):
        raise ValueError(f"TrafficConfig.parking must be 'scatter' or 'rows', "
                         f"not {config.traffic.parking!r}")
    if config.traffic.parking == "rows" and not config.traffic.vehicle_mix:
        raise ValueError("TrafficConfig.parking = 'rows' needs a TrafficConfig.vehicle_mix")
    rng = np.random.default_rng([seed, seq])
    stream = lambda k: np.random.default_rng([seed, seq, k])  # noqa: E731
    models = [load_car_mesh(p) for p in (bundled_mesh_paths() if meshes is None else meshes)]
    rig = make_rig(config)
    track = ego_track(config, frames, rng)
    ego_s = track[0]
    road = config.road
    cl = Centreline(ego_s[0] - road.behind, ego_s[-1] + road.ahead,
                    heading0=float(rng.uniform(-np.pi, np.pi)),
                    curvature=float(rng.uniform(-1, 1)) * road.max_curvature,
                    wavelength=float(rng.uniform(*road.curvature_wavelength)),
                    phase=float(rng.uniform(0, 2 * np.pi)))
    rows = config.traffic.parking == "rows"
    segments, widths = [], None
    if rows:
        extent = config.parking.extent
        segments = draw_segments(stream(STREAM_PARKING), config.parking, ego_s[0] + extent[0],
                                 ego_s[-1] + extent[1])
        widths = strip_widths(segments, config.parking)
    static, buildings = build_static(cl, road, rng, widths)
    attitude = _camera_attitude(stream(STREAM_CAMERA), config, rig)
    poses, cams = ego_poses(config, rig, cl, track,
                            (0.0, 0.0) if attitude is None else attitude[1])

    deck = None
    if config.traffic.vehicle_mix:
        deck = VehicleDeck(stream(STREAM_VEHICLES), config.traffic.vehicle_mix, models,
                           config.vehicles, config.traffic.mesh_scale_jitter)
    traffic_rng = stream(STREAM_TRAFFIC) if rows else rng
    cars: list[SynthCar] = []
    kinds = (("dynamic", n_dynamic),) if rows else (("dynamic", n_dynamic), ("parked", n_static))
    for kind, count in kinds:
        for _ in range(count):
            for _try in range(config.traffic.max_tries):
                entry, model = deck.draw() if deck else ("", _pick_model(rng, config, models))
                place = place_dynamic if kind == "dynamic" else place_scattered
                car = place(traffic_rng, config, cl, ego_s, model, len(cars) + 1)
                if car is not None and not collides(car, cars, frames, config.traffic.min_gap):
                    cars.append(car)
                    break
                if deck:
                    deck.put_back(entry)
            else:
                raise PlacementError(
                    f"could not place {kind} car {len(cars) + 1} without collisions after "
                    f"{config.traffic.max_tries} tries: ask for fewer cars or more frames")
    edges = road_edges(road, widths)
    if rows:
        parked = place_rows(stream(STREAM_PARKING), config, cl, segments, edges, deck, cars,
                            frames, len(cars) + 1)
        order = np.argsort([cl.to_road(c.centre0[None, :2])[0][0] for c in parked], kind="stable")
        kept = sorted(order[:n_static])
        cars += [replace(parked[k], instance_id=len(cars) + 1 + j) for j, k in enumerate(kept)]
    props = []
    if config.props.density:
        parts, props = place_props(stream(STREAM_PROPS), config.props, road, cl, edges, ego_s,
                                   cars)
        static.extend(parts)
    frame_ids = [config.first_frame + i for i in range(frames)]
    return SynthWorld(config, sequence_name(seq), frame_ids, rig, cl, static, buildings, cars,
                      poses, cams, props, None if attitude is None else attitude[0],
                      [(g.side, g.s0, g.s1, g.layout, g.angle_deg) for g in segments])


def _camera_attitude(rng: np.random.Generator, config: SynthConfig, rig: Rig
                     ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """Drawn camera (pitch, roll) in degrees and the vehicle attitude (radians) that gives them;
    None when the rig config draws neither (a range left None keeps the level vehicle's value)."""
    r = config.rig
    if r.camera_pitch_deg is None and r.camera_roll_deg is None:
        return None
    level = camera_pitch_roll(vehicle_pose(rig, 0.0, 0.0, 0.0, np.zeros(3))[1])
    pitch = level[0] if r.camera_pitch_deg is None else float(rng.uniform(*r.camera_pitch_deg))
    roll = level[1] if r.camera_roll_deg is None else float(rng.uniform(*r.camera_roll_deg))
    return (pitch, roll), vehicle_attitude_for(rig, pitch, roll)


__all__ = ["STREAM_CAMERA", "STREAM_PARKING", "STREAM_PROPS", "STREAM_TRAFFIC",
           "STREAM_VEHICLES", "build_world", "place_dynamic", "place_scattered"]
