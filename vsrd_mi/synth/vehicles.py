"""Procedural vehicles of eight classes: city car, hatchback, sedan, estate, SUV, pickup, van and
low sports car (the class table and the real vehicles behind its ranges: ``docs/synthetic.md``).

A vehicle is built in the car frame (x forward, y left, z up, metres) from

- a lower body: the side profile (nose, bonnet rising to the belt line, boot deck or bed floor,
  tail) with wheel arches cut out, extruded across the body width;
- a greenhouse: the convex hull of the cabin's outline at the belt line and at the roof
  (windscreen, roof, rear window; the roof is painted, the rest is glass);
- an open cargo bed for a pickup (floor, side walls and tailgate);
- two door mirrors, which stick out of the body sides;
- four wheels (tyres with a hub disc), the lowest vertex of each on the ground.

The profile is asymmetric front to back as on real cars: the bonnet's length, the windscreen's
and the rear window's runs and the boot or tail length are drawn per class, so where the cabin
stands along the car depends on the class (far forward on a van, behind the middle on a sports
car). The ground-truth box is the tight box of the whole mesh, mirrors included: its size is
``(length, body width + 2 * mirror, height)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import shapely
import trimesh
from shapely.geometry import Point, Polygon

from .cars import (BODY, GLASS, PLATE_HALF_WIDTH, RIM, TYRE, CarModel, LampLayout, scaled,
                   with_mesh_lamps)

Range = tuple[float, float]


@dataclass(frozen=True)
class VehicleClass:
    """Ranges of one procedural vehicle class; every value is drawn uniformly per vehicle.

    Lengths, widths, heights and radii are metres. The profile runs (``bonnet`` .. ``tail``) are
    fractions of the length, measured along x: front end to windscreen base, windscreen base to
    roof front, roof rear to rear-window base, rear-window base to the rear end (boot, hatch, or a
    pickup's bed). Heights of the belt line are fractions of the height, those of the bonnet's
    front edge (``nose``) and of the boot deck / tail top (``deck``) fractions of the belt height.
    """

    name: str
    length: Range
    #: Body width without mirrors.
    body_width: Range
    height: Range
    bonnet: Range
    windscreen: Range
    backlight: Range
    tail: Range
    belt: Range
    nose: Range
    deck: Range
    #: Front end to the front axle and rear axle to the rear end, fractions of the length.
    front_overhang: Range
    rear_overhang: Range
    wheel_radius: Range
    #: How far each door mirror sticks out of the body side.
    mirror: Range
    #: Roof width as a fraction of the body width.
    roof_width: Range
    #: Open cargo bed over the ``tail`` run (a pickup).
    bed: bool = False


#: The default class table (sources of the ranges: docs/synthetic.md).
VEHICLE_CLASSES: tuple[VehicleClass, ...] = (
    VehicleClass("city_car", length=(3.30, 3.75), body_width=(1.60, 1.70), height=(1.45, 1.60),
                 bonnet=(0.15, 0.19), windscreen=(0.17, 0.21), backlight=(0.07, 0.11),
                 tail=(0.03, 0.06), belt=(0.54, 0.60), nose=(0.72, 0.82), deck=(0.90, 1.00),
                 front_overhang=(0.17, 0.20), rear_overhang=(0.13, 0.17),
                 wheel_radius=(0.27, 0.30), mirror=(0.08, 0.11), roof_width=(0.78, 0.86)),
    VehicleClass("hatchback", length=(3.95, 4.40), body_width=(1.70, 1.82), height=(1.40, 1.52),
                 bonnet=(0.20, 0.24), windscreen=(0.16, 0.19), backlight=(0.08, 0.12),
                 tail=(0.04, 0.08), belt=(0.54, 0.60), nose=(0.70, 0.80), deck=(0.90, 1.00),
                 front_overhang=(0.19, 0.22), rear_overhang=(0.16, 0.19),
                 wheel_radius=(0.30, 0.33), mirror=(0.10, 0.13), roof_width=(0.76, 0.84)),
    VehicleClass("sedan", length=(4.55, 5.00), body_width=(1.78, 1.88), height=(1.40, 1.50),
                 bonnet=(0.23, 0.27), windscreen=(0.14, 0.17), backlight=(0.11, 0.14),
                 tail=(0.16, 0.21), belt=(0.55, 0.61), nose=(0.70, 0.80), deck=(0.95, 1.02),
                 front_overhang=(0.18, 0.21), rear_overhang=(0.21, 0.24),
                 wheel_radius=(0.31, 0.34), mirror=(0.10, 0.13), roof_width=(0.74, 0.82)),
    VehicleClass("estate", length=(4.55, 4.95), body_width=(1.78, 1.90), height=(1.45, 1.55),
                 bonnet=(0.22, 0.25), windscreen=(0.14, 0.16), backlight=(0.03, 0.06),
                 tail=(0.03, 0.05), belt=(0.55, 0.60), nose=(0.70, 0.80), deck=(0.92, 1.00),
                 front_overhang=(0.18, 0.21), rear_overhang=(0.20, 0.23),
                 wheel_radius=(0.31, 0.34), mirror=(0.10, 0.13), roof_width=(0.76, 0.84)),
    VehicleClass("suv", length=(4.40, 5.05), body_width=(1.82, 2.00), height=(1.60, 1.87),
                 bonnet=(0.20, 0.24), windscreen=(0.12, 0.15), backlight=(0.04, 0.07),
                 tail=(0.02, 0.05), belt=(0.57, 0.63), nose=(0.80, 0.90), deck=(0.92, 1.00),
                 front_overhang=(0.18, 0.21), rear_overhang=(0.19, 0.22),
                 wheel_radius=(0.35, 0.39), mirror=(0.10, 0.13), roof_width=(0.78, 0.86)),
    VehicleClass("pickup", length=(5.20, 5.95), body_width=(1.85, 2.08), height=(1.78, 1.98),
                 bonnet=(0.21, 0.25), windscreen=(0.10, 0.12), backlight=(0.01, 0.02),
                 tail=(0.28, 0.34), belt=(0.66, 0.72), nose=(0.88, 0.96), deck=(0.95, 1.00),
                 front_overhang=(0.15, 0.18), rear_overhang=(0.19, 0.23),
                 wheel_radius=(0.37, 0.41), mirror=(0.15, 0.21), roof_width=(0.82, 0.90),
                 bed=True),
    VehicleClass("van", length=(4.85, 5.45), body_width=(1.90, 2.10), height=(1.88, 2.10),
                 bonnet=(0.08, 0.12), windscreen=(0.12, 0.15), backlight=(0.01, 0.03),
                 tail=(0.01, 0.03), belt=(0.44, 0.50), nose=(0.85, 0.95), deck=(0.95, 1.00),
                 front_overhang=(0.17, 0.20), rear_overhang=(0.17, 0.21),
                 wheel_radius=(0.32, 0.35), mirror=(0.15, 0.21), roof_width=(0.88, 0.94)),
    VehicleClass("sports", length=(3.90, 4.65), body_width=(1.73, 1.95), height=(1.20, 1.35),
                 bonnet=(0.27, 0.32), windscreen=(0.15, 0.18), backlight=(0.18, 0.24),
                 tail=(0.04, 0.08), belt=(0.56, 0.62), nose=(0.78, 0.88), deck=(0.92, 1.00),
                 front_overhang=(0.19, 0.22), rear_overhang=(0.19, 0.23),
                 wheel_radius=(0.30, 0.33), mirror=(0.10, 0.13), roof_width=(0.70, 0.78)),
)


@dataclass(frozen=True)
class VehicleConfig:
    """The procedural vehicle classes and the details shared by all of them (metres)."""

    classes: tuple[VehicleClass, ...] = VEHICLE_CLASSES
    #: The roof is at least this share of the length (the four profile runs are scaled down
    #: together when their draws leave less).
    min_roof_fraction: float = 0.12
    #: Width of the greenhouse at the belt line as a fraction of the body width (tumblehome).
    cabin_width_fraction: float = 0.96
    #: Tyre width range, and the gap between the tyre's outer face and the body side (range).
    wheel_width: Range = (0.19, 0.26)
    wheel_inset: Range = (0.015, 0.04)
    #: Hub disc: radius as a fraction of the wheel radius, and how far it stands out of the tyre.
    hub_fraction: float = 0.62
    hub_proud: float = 0.005
    #: How deep the hub disc reaches into the tyre.
    hub_depth: float = 0.01
    #: Body bottom above the ground as a fraction of the wheel radius.
    clearance_fraction: Range = (0.45, 0.65)
    #: Gap between a tyre and its wheel arch.
    arch_gap: Range = (0.02, 0.07)
    #: Least body left above a wheel arch; wheels are made smaller when the body is too low.
    arch_wall: float = 0.06
    #: The bumpers' lowest edges are set back this far from the car's ends.
    bumper_setback: Range = (0.05, 0.15)
    #: Height of the bumper's most protruding point above the body bottom, as a fraction of the
    #: distance from the body bottom to the bonnet's front edge (or the tail top).
    bumper_fraction: Range = (0.30, 0.45)
    #: Run of the rounded edge from the bumper's front to the bonnet (and to the deck).
    nose_round: Range = (0.08, 0.18)
    #: Radius of the body's plan corners (seen from above, where the bumpers wrap round to the
    #: sides; the lower body and the cabin, not a pickup's bed walls). (0, 0), the default, keeps
    #: the plan a rectangle, the side profile extruded across the width. A range of equal ends
    #: is that radius and draws nothing, so the vehicles and the street they stand in are drawn
    #: as with square corners.
    plan_corner: Range = (0.0, 0.0)
    #: Longest edge of the side profile where the plan corners are rounded (its vertices are what
    #: the rounding moves).
    plan_segment: float = 0.04
    #: Door mirrors: length along x, height, set-back behind the windscreen base (ranges).
    mirror_length: Range = (0.20, 0.28)
    mirror_height: Range = (0.13, 0.18)
    mirror_setback: Range = (0.05, 0.20)
    #: How far a mirror's base reaches into the body side.
    mirror_embed: float = 0.02
    #: Pickup bed: wall thickness.
    bed_wall: float = 0.05
    #: Facets around a wheel, and segments per quarter circle of a wheel arch.
    wheel_sections: int = 16
    arch_segments: int = 6
    #: Lamps: height of the headlamp band as a fraction of the nose slope, its ``|y|`` band and
    #: the amber indicator's start as fractions of the half body width; the rear lamps' band the
    #: same way on the tail.
    head_band: Range = (0.35, 1.0)
    head_y: Range = (0.50, 0.95)
    indicator_y: float = 0.86
    tail_band: Range = (0.35, 1.0)
    tail_y: Range = (0.58, 0.97)
    #: Number plates: height above the body bottom of the front / rear plate's lower edge.
    plate_front_lift: float = 0.04
    plate_rear_lift: float = 0.30
    #: Plate height (a European plate is 520 mm x 110 mm).
    plate_height: float = 0.11

    def __post_init__(self) -> None:
        lo, hi = self.plan_corner
        if not 0.0 <= lo <= hi:
            raise ValueError(f"VehicleConfig.plan_corner must be a range 0 <= lo <= hi (m), got {self.plan_corner}")
        if self.plan_segment <= 0:
            raise ValueError(f"VehicleConfig.plan_segment must be > 0 m, got {self.plan_segment}")

    @property
    def class_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.classes)

    def vehicle_class(self, name: str) -> VehicleClass:
        """The class called ``name`` (ValueError naming the known classes otherwise)."""
        for c in self.classes:
            if c.name == name:
                return c
        raise ValueError(f"unknown vehicle class {name!r} (VehicleConfig.classes has "
                         f"{', '.join(self.class_names)})")


def extrude_profile(profile: Polygon, y0: float, y1: float) -> tuple[np.ndarray, np.ndarray]:
    """Prism of a side profile ``(x, z)`` between ``y = y0`` and ``y = y1`` (outward normals).

    The caps are the profile's constrained Delaunay triangles; the walls are one quad per edge
    of the exterior ring. Returns ``(vertices (V, 3), faces (F, 3))``.
    """
    tris = shapely.constrained_delaunay_triangles(profile)
    verts, faces = [], []
    for tri in tris.geoms:
        xz = np.asarray(tri.exterior.coords)[:3]
        if (xz[1, 0] - xz[0, 0]) * (xz[2, 1] - xz[0, 1]) - \
                (xz[1, 1] - xz[0, 1]) * (xz[2, 0] - xz[0, 0]) < 0:
            xz = xz[::-1]  # counter-clockwise in (x, z): its normal (x cross z) is -y
        for y, order in ((y0, (0, 1, 2)), (y1, (0, 2, 1))):
            base = len(verts)
            verts += [(p[0], y, p[1]) for p in xz]
            faces.append([base + k for k in order])
    ring = shapely.geometry.polygon.orient(profile, 1.0).exterior  # counter-clockwise
    xz = np.asarray(ring.coords)[:-1]
    for a, b in zip(xz, np.roll(xz, -1, axis=0)):
        base = len(verts)
        verts += [(a[0], y0, a[1]), (b[0], y0, b[1]), (b[0], y1, b[1]), (a[0], y1, a[1])]
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)


def round_plan_corners(verts: np.ndarray, half: float, hw: float, radius: float) -> np.ndarray:
    """``verts`` (V, 3) of a body spanning ``|x| <= half``, ``|y| <= hw`` with each point's ``|y|``
    capped at the quarter circle of ``radius`` in the plan's corners (a copy)."""
    out = np.array(verts, dtype=np.float64)
    into = np.clip(np.abs(out[:, 0]) - (half - radius), 0.0, radius)
    limit = hw - radius + np.sqrt(np.maximum(radius * radius - into * into, 0.0))
    out[:, 1] = np.sign(out[:, 1]) * np.minimum(np.abs(out[:, 1]), limit)
    return out


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]
         ) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.box(bounds=[lo, hi])
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Convex hull of ``points``: vertices, faces and face normals."""
    mesh = trimesh.convex.convex_hull(points)
    return (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64),
            np.asarray(mesh.face_normals))


def _wheel(x: float, radius: float, y_in: float, y_out: float, sections: int
           ) -> tuple[np.ndarray, np.ndarray]:
    """A wheel prism about the y axis with one vertex at the bottom (exactly z = 0)."""
    angles = -0.5 * np.pi + 2.0 * np.pi * np.arange(sections) / sections
    ring = np.stack([x + radius * np.cos(angles), radius + radius * np.sin(angles)], axis=1)
    ring[0] = (x, 0.0)  # cos(-pi/2) is 6e-17, not 0
    pts = np.array([(p[0], y, p[1]) for y in (y_in, y_out) for p in ring])
    verts, faces, _ = _hull(pts)
    return verts, faces


@dataclass(frozen=True)
class Profile:
    """The drawn side profile of one vehicle (metres, car frame; x = 0 at the middle)."""

    length: float
    body_width: float
    height: float
    mirror: float
    #: x of the windscreen base, roof front, roof rear and rear-window base.
    windscreen_base: float
    roof_front: float
    roof_rear: float
    backlight_base: float
    belt: float
    nose: float
    deck: float
    clearance: float
    wheel_radius: float
    #: x of the front and rear axles.
    front_axle: float
    rear_axle: float


def draw_profile(rng: np.random.Generator, vclass: VehicleClass, config: VehicleConfig) -> Profile:
    """Draw one vehicle's dimensions and side profile from its class's ranges."""
    u = lambda r: float(rng.uniform(*r))  # noqa: E731
    length, width, height = u(vclass.length), u(vclass.body_width), u(vclass.height)
    runs = np.array([u(vclass.bonnet), u(vclass.windscreen), u(vclass.backlight), u(vclass.tail)])
    if runs.sum() > 1.0 - config.min_roof_fraction:
        runs *= (1.0 - config.min_roof_fraction) / runs.sum()
    bonnet, windscreen, backlight, tail = runs * length
    half = 0.5 * length
    belt = height * u(vclass.belt)
    radius = u(vclass.wheel_radius)
    return Profile(length, width, height, u(vclass.mirror), half - bonnet,
                   half - bonnet - windscreen, -half + tail + backlight, -half + tail, belt,
                   belt * u(vclass.nose), belt * u(vclass.deck),
                   radius * u(config.clearance_fraction), radius,
                   half - length * u(vclass.front_overhang),
                   -half + length * u(vclass.rear_overhang))


def build_vehicle(rng: np.random.Generator, vclass: VehicleClass | str,
                  config: VehicleConfig = VehicleConfig()) -> CarModel:
    """A random vehicle of class ``vclass`` (a :class:`VehicleClass` or a class name).

    The tight box of the result is exactly ``(length, body_width + 2 * mirror, height)`` with the
    drawn values, its lowest vertex at z = 0 and its centre at ``x = y = 0``.
    """
    if isinstance(vclass, str):
        vclass = config.vehicle_class(vclass)
    p = draw_profile(rng, vclass, config)
    u = lambda r: float(rng.uniform(*r))  # noqa: E731
    half, hw = 0.5 * p.length, 0.5 * p.body_width
    nose_round = min(u(config.nose_round), 0.5 * (half - p.windscreen_base))
    tail_round = min(u(config.nose_round), 0.5 * (p.backlight_base + half))
    bumper_front = p.clearance + u(config.bumper_fraction) * (p.nose - p.clearance)
    bumper_rear = p.clearance + u(config.bumper_fraction) * (p.deck - p.clearance)
    gap = u(config.arch_gap)
    # the wheels and arches must leave arch_wall of body below the bonnet / deck / bed floor
    lowest_top = min(_profile_top(p, nose_round, p.front_axle),
                     _profile_top(p, tail_round, p.rear_axle))
    radius = min(p.wheel_radius, 0.5 * (lowest_top - gap - config.arch_wall))
    clearance = min(p.clearance, radius)
    floor = 2.0 * radius + gap + config.arch_wall  # pickup bed floor, just above the rear arch
    outline = [(-half + u(config.bumper_setback), clearance),
               (half - u(config.bumper_setback), clearance),
               (half, bumper_front), (half - nose_round, p.nose),
               (p.windscreen_base, p.belt), (p.backlight_base, p.belt)]
    if vclass.bed:
        outline += [(p.backlight_base, floor), (-half, floor)]
    else:
        outline += [(-half + tail_round, p.deck), (-half, bumper_rear)]
    body = Polygon(outline)
    for x in (p.front_axle, p.rear_axle):
        body = body.difference(Point(x, radius).buffer(radius + gap, quad_segs=config.arch_segments))
    if body.geom_type != "Polygon" or not body.is_valid:
        raise ValueError(f"vehicle class {vclass.name!r}: its ranges give a side profile that "
                         f"falls apart at the wheel arches ({body.geom_type})")

    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | int]] = []
    lo, hi = config.plan_corner
    corner = 0.0
    if hi > 0:
        corner = min(lo if lo == hi else u(config.plan_corner), hw, PLAN_CORNER_MAX_SHARE * half)
        prism = extrude_profile(shapely.segmentize(body, config.plan_segment), -hw, hw)
        parts.append((round_plan_corners(prism[0], half, hw, corner), prism[1], BODY))
    else:
        parts.append((*extrude_profile(body, -hw, hw), BODY))
    cw, rw = config.cabin_width_fraction * hw, u(vclass.roof_width) * hw
    cabin = np.array([(x, s * w, z) for x0, x1, w, z in
                      ((p.backlight_base, p.windscreen_base, cw, p.belt),
                       (p.roof_rear, p.roof_front, rw, p.height))
                      for x in (x0, x1) for s in (-1.0, 1.0)])
    if corner > 0:  # a cabin reaching into the rounded corners (a van's) stays inside them
        cabin = round_plan_corners(cabin, half, hw, corner)
    cv, cf, cn = _hull(cabin)
    parts.append((cv, cf, np.where(cn[:, 2] > ROOF_MIN_NORMAL_Z, BODY, GLASS)))
    if vclass.bed:
        t = config.bed_wall
        for lo, hi in (((-half, hw - t, floor), (p.backlight_base, hw, p.belt)),
                       ((-half, -hw, floor), (p.backlight_base, -hw + t, p.belt)),
                       ((-half, -hw, floor), (-half + t, hw, p.belt))):
            parts.append((*_box(lo, hi), BODY))
    m_len, m_h, m_back = u(config.mirror_length), u(config.mirror_height), u(config.mirror_setback)
    x1 = p.windscreen_base - m_back
    for s in (-1.0, 1.0):
        ys = sorted((s * (hw - config.mirror_embed), s * (hw + p.mirror)))
        parts.append((*_box((x1 - m_len, ys[0], p.belt), (x1, ys[1], p.belt + m_h)), BODY))
    tyre_w, inset = u(config.wheel_width), u(config.wheel_inset)
    for x in (p.front_axle, p.rear_axle):
        for s in (-1.0, 1.0):
            y_out, y_in = s * (hw - inset), s * (hw - inset - tyre_w)
            parts.append((*_wheel(x, radius, y_in, y_out, config.wheel_sections), TYRE))
            hub = _wheel(x, config.hub_fraction * radius, y_out - s * config.hub_depth,
                         y_out + s * config.hub_proud, config.wheel_sections)
            hub[0][:, 2] += (1.0 - config.hub_fraction) * radius
            parts.append((*hub, RIM))

    verts, faces, mats, offset = [], [], [], 0
    for v, f, m in parts:
        verts.append(v)
        faces.append(f + offset)
        mats.append(np.broadcast_to(np.asarray(m, dtype=np.int8), (len(f),)))
        offset += len(v)
    lamps = _lamps(p, config, clearance, bumper_front, nose_round, bumper_rear, tail_round,
                   floor if vclass.bed else None)
    return CarModel(f"vehicle-{vclass.name}", np.concatenate(verts), np.concatenate(faces),
                    np.concatenate(mats), vclass.name, lamps)


#: The plan corners' radius is at most this share of the half length (and at most the half
#: width): the rounding stays in the end quarters of the car.
PLAN_CORNER_MAX_SHARE = 0.5

#: Greenhouse faces whose normal points up more steeply than this are roof (painted), not glass.
ROOF_MIN_NORMAL_Z = 0.9


def _profile_top(p: Profile, nose_round: float, x: float) -> float:
    """Height of the lower body's top edge at ``x`` for the arch check (bed floor excluded)."""
    half = 0.5 * p.length
    xs = [-half, -half + nose_round, p.backlight_base, p.windscreen_base, half - nose_round, half]
    zs = [p.deck, p.deck, p.belt, p.belt, p.nose, p.nose]
    return float(np.interp(x, xs, zs))


def _lamps(p: Profile, config: VehicleConfig, clearance: float, bumper_front: float,
           nose_round: float, bumper_rear: float, tail_round: float,
           bed_floor: float | None) -> LampLayout:
    """Lamp and plate bands on the nose slope and the tail (a pickup's on the tailgate)."""
    hw = 0.5 * p.body_width
    head = (bumper_front + config.head_band[0] * (p.nose - bumper_front),
            bumper_front + config.head_band[1] * (p.nose - bumper_front))
    tail_lo, tail_hi = (bumper_rear, p.deck) if bed_floor is None else (bed_floor, p.belt)
    tail = (tail_lo + config.tail_band[0] * (tail_hi - tail_lo),
            tail_lo + config.tail_band[1] * (tail_hi - tail_lo))
    rear_plate = clearance + config.plate_rear_lift
    return LampLayout(head, (config.head_y[0] * hw, config.head_y[1] * hw),
                      config.indicator_y * hw, tail,
                      (config.tail_y[0] * hw, config.tail_y[1] * hw),
                      (clearance + config.plate_front_lift,
                       clearance + config.plate_front_lift + config.plate_height),
                      (rear_plate, rear_plate + config.plate_height), PLATE_HALF_WIDTH)


def random_vehicle(rng: np.random.Generator, config: VehicleConfig = VehicleConfig()) -> CarModel:
    """A vehicle of a class drawn uniformly from ``config.classes``."""
    return build_vehicle(rng, config.classes[int(rng.integers(len(config.classes)))], config)


#: Entry of a vehicle mix that stands for every mesh file.
ALL_MESHES = "meshes"


class VehicleDeck:
    """Draws vehicles from a mix so that every entry comes up in turn.

    ``mix`` holds (entry, weight) pairs: a class of ``config``, a mesh model's name, or
    :data:`ALL_MESHES`. The deck holds each entry ``weight`` times in a random order and is
    refilled when empty; an entry handed back with :meth:`put_back` (its vehicle did not fit)
    goes to the bottom of the deck. Mesh models carry lamps and plates and are scaled by
    ``1 + U(-mesh_scale_jitter, mesh_scale_jitter)``.
    """

    def __init__(self, rng: np.random.Generator, mix: Sequence[tuple[str, int]],
                 meshes: Sequence[CarModel], config: VehicleConfig, mesh_scale_jitter: float):
        self.rng, self.config, self.jitter = rng, config, mesh_scale_jitter
        self.meshes = {m.name: m for m in meshes}
        self.entries: list[str] = []
        for name, weight in mix:
            if weight < 0 or int(weight) != weight:
                raise ValueError(f"vehicle_mix: weight of {name!r} must be a non-negative integer")
            names = sorted(self.meshes) if name == ALL_MESHES else [name]
            for n in names:
                if n not in self.meshes and n not in config.class_names:
                    raise ValueError(
                        f"vehicle_mix: {n!r} is neither a vehicle class "
                        f"({', '.join(config.class_names)}) nor a mesh file "
                        f"({', '.join(sorted(self.meshes)) or 'none given'})")
                self.entries += [n] * int(weight)
        if not self.entries:
            raise ValueError("vehicle_mix: no vehicle to draw (every weight is 0 or no mesh "
                             "file was given)")
        self.deck: list[str] = []

    def draw(self) -> tuple[str, CarModel]:
        """The next entry of the deck and a new vehicle of it."""
        if not self.deck:
            self.deck = [self.entries[k] for k in self.rng.permutation(len(self.entries))]
        name = self.deck.pop(0)
        if name in self.meshes:
            factor = 1.0 + float(self.rng.uniform(-self.jitter, self.jitter))
            return name, scaled(with_mesh_lamps(self.meshes[name]), factor)
        return name, build_vehicle(self.rng, name, self.config)

    def put_back(self, name: str) -> None:
        """Return an entry whose vehicle was not used to the bottom of the deck."""
        self.deck.append(name)


__all__ = ["ALL_MESHES", "VehicleClass", "VehicleDeck", "VehicleConfig", "VEHICLE_CLASSES", "Profile", "build_vehicle",
           "draw_profile", "extrude_profile", "random_vehicle", "round_plan_corners"]
