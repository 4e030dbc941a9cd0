"""Props: things that are not cars, standing in front of and between the parked cars.

Street lamps (pole), traffic signs (a post, semantic pole, and a plate, semantic traffic sign),
trees (trunk and crown, vegetation: stuff without an instance id), pedestrians (person) and
wheelie bins (trash bin). They stand on the sidewalks, a little behind the kerb, and pedestrians
and bins also in the parking strip between parked cars. Every prop has its own semantic id and
(except trees) its own instance id within its class; car ids are never used.
"""

from __future__ import annotations

import numpy as np
import trimesh
from shapely.geometry import Point

from .config import PROP_KINDS, PropConfig, RoadConfig
from .world import (PROP, SEM_PERSON, SEM_POLE, SEM_TRAFFIC_SIGN, SEM_TRASH_BIN, SEM_VEGETATION,
                    Centreline, MeshParts, PropPart, SynthCar, rot_z)

#: Radius (metres) of the ground circle a pedestrian covers, for the collision checks.
PERSON_FOOTPRINT = 0.3
#: Subdivisions of the icospheres of heads and tree crowns.
ICO_SUBDIVISIONS = 1
#: Random radial jitter of a tree crown's vertices (fraction of its radius).
CROWN_JITTER = 0.2
#: Street lamp head (length towards the road, width, height), metres.
LAMP_HEAD = (0.6, 0.25, 0.15)
#: Thickness of a sign plate, metres.
SIGN_THICKNESS = 0.03
#: Shares of a pedestrian's height taken by the legs and the torso (the head takes the rest).
LEGS_SHARE, TORSO_SHARE = 0.47, 0.40
#: A pedestrian's legs span this share of the torso's width and depth.
LEGS_SPAN = 0.7
#: A trunk reaches this share of the crown radius into the crown.
TRUNK_INTO_CROWN = 0.3


def _mesh(m: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def _cylinder(radius: float, height: float, sections: int) -> tuple[np.ndarray, np.ndarray]:
    """Upright cylinder standing on z = 0."""
    v, f = _mesh(trimesh.creation.cylinder(radius=radius, height=height, sections=sections))
    v[:, 2] += 0.5 * height
    return v, f


def _box(size: tuple[float, float, float], base_z: float) -> tuple[np.ndarray, np.ndarray]:
    """Box centred on the z axis with its bottom at ``base_z``."""
    v, f = _mesh(trimesh.creation.box(extents=size))
    v[:, 2] += base_z + 0.5 * size[2]
    return v, f


class PropBuilder:
    """Collects prop meshes (in world coordinates) and their coloured parts."""

    def __init__(self, rng: np.random.Generator, cfg: PropConfig, first_part: int = 0):
        self.rng, self.cfg = rng, cfg
        self.parts = MeshParts()
        self.props: list[PropPart] = []
        self.first_part = first_part
        self.counts: dict[int, int] = {}

    def _pick(self, palette: tuple[tuple[int, int, int], ...]) -> tuple[int, int, int]:
        return palette[int(self.rng.integers(len(palette)))]

    def _instance(self, semantic: int) -> int:
        self.counts[semantic] = self.counts.get(semantic, 0) + 1
        return self.counts[semantic]

    def _add(self, kind: str, verts: np.ndarray, faces: np.ndarray, place: np.ndarray,
             yaw: float, semantic: int, instance: int, rgb: tuple[int, int, int]) -> None:
        world = verts @ rot_z(yaw).T + place
        self.parts.add(world, faces, PROP, semantic, instance,
                       self.first_part + len(self.props))
        self.props.append(PropPart(kind, rgb, int(self.rng.integers(1 << 30))))

    def add(self, kind: str, place: np.ndarray, yaw: float, road_yaw: float) -> None:
        """Add one prop of ``kind`` standing at world point ``place`` (x, y, ground z).

        ``yaw`` turns the prop about its axis; ``road_yaw`` is the traffic direction beside it
        (signs face it, a lamp head reaches over the road, a quarter turn to its left).
        """
        u = lambda r: float(self.rng.uniform(*r))  # noqa: E731
        cfg = self.cfg
        if kind == "pole":
            height = u(cfg.pole_height)
            inst, rgb = self._instance(SEM_POLE), self._pick(cfg.pole_palette)
            self._add(kind, *_cylinder(u(cfg.pole_radius), height, cfg.sections), place, yaw,
                      SEM_POLE, inst, rgb)
            head = _box(LAMP_HEAD, height - LAMP_HEAD[2])
            self._add(kind, head[0] + [0.5 * LAMP_HEAD[0], 0.0, 0.0], head[1], place,
                      road_yaw + 0.5 * np.pi, SEM_POLE, inst, rgb)
        elif kind == "sign":
            height, size = u(cfg.sign_height), u(cfg.sign_size)
            self._add("sign_post", *_cylinder(u(cfg.sign_post_radius), height, cfg.sections),
                      place, yaw, SEM_POLE, self._instance(SEM_POLE), self._pick(cfg.pole_palette))
            plate = _box((SIGN_THICKNESS, size, size), height)
            self._add(kind, *plate, place, road_yaw, SEM_TRAFFIC_SIGN,
                      self._instance(SEM_TRAFFIC_SIGN), self._pick(cfg.sign_palette))
        elif kind == "tree":
            trunk_h, crown_r = u(cfg.trunk_height), u(cfg.crown_radius)
            self._add("trunk", *_cylinder(u(cfg.trunk_radius), trunk_h + TRUNK_INTO_CROWN * crown_r,
                                          cfg.sections), place, yaw, SEM_VEGETATION, 0,
                      cfg.bark_rgb)
            sphere = trimesh.creation.icosphere(subdivisions=ICO_SUBDIVISIONS)
            v = np.asarray(sphere.vertices) * crown_r * self.rng.uniform(
                1.0 - CROWN_JITTER, 1.0 + CROWN_JITTER, size=(len(sphere.vertices), 1))
            v[:, 2] += trunk_h + crown_r
            self._add("crown", *_mesh(trimesh.convex.convex_hull(v)), place, yaw,
                      SEM_VEGETATION, 0, self._pick(cfg.foliage_palette))
        elif kind == "pedestrian":
            h, w, d = u(cfg.person_height), u(cfg.person_width), u(cfg.person_depth)
            inst = self._instance(SEM_PERSON)
            legs, torso = LEGS_SHARE * h, TORSO_SHARE * h
            head_r = 0.5 * (1.0 - LEGS_SHARE - TORSO_SHARE) * h
            self._add("legs", *_box((LEGS_SPAN * d, LEGS_SPAN * w, legs), 0.0), place, yaw,
                      SEM_PERSON, inst, self._pick(cfg.clothes_palette))
            self._add("torso", *_box((d, w, torso), legs), place, yaw, SEM_PERSON, inst,
                      self._pick(cfg.clothes_palette))
            v, f = _mesh(trimesh.creation.icosphere(subdivisions=ICO_SUBDIVISIONS, radius=head_r))
            v[:, 2] += legs + torso + head_r
            self._add("head", v, f, place, yaw, SEM_PERSON, inst, self._pick(cfg.skin_palette))
        elif kind == "bin":
            size = tuple(u(r) for r in cfg.bin_size)
            self._add(kind, *_box(size, 0.0), place, yaw, SEM_TRASH_BIN,
                      self._instance(SEM_TRASH_BIN), self._pick(cfg.bin_palette))
        else:
            raise ValueError(f"PropConfig.density: unknown prop kind {kind!r} "
                             f"(known: {', '.join(PROP_KINDS)})")


def footprint_radius(kind: str, cfg: PropConfig) -> float:
    """Radius of the circle that a prop of ``kind`` covers on the ground (its largest draw)."""
    return {"pole": cfg.pole_radius[1], "sign": cfg.sign_post_radius[1],
            "tree": cfg.trunk_radius[1], "pedestrian": PERSON_FOOTPRINT,
            "bin": 0.5 * float(np.hypot(cfg.bin_size[0][1], cfg.bin_size[1][1]))}[kind]


def place_props(rng: np.random.Generator, cfg: PropConfig, road: RoadConfig, cl: Centreline,
                edges: tuple[float, float], ego_s: np.ndarray, cars: list[SynthCar],
                first_part: int = 0) -> tuple[MeshParts, list[PropPart]]:
    """Props along both sides of ``[ego_s[0] + extent[0], ego_s[-1] + extent[1]]``.

    ``edges`` = (right, left) kerb offsets. Props keep ``cfg.clearance`` from every car's
    footprint (parked cars at frame 0; moving cars stay in the lanes, which no prop enters) and
    from each other.
    """
    builder = PropBuilder(rng, cfg, first_part)
    s0, s1 = ego_s[0] + cfg.extent[0], ego_s[-1] + cfg.extent[1]
    parked = [c.footprint(0) for c in cars if not c.dynamic]
    taken: list[Point] = []
    for side, edge in zip((-1, 1), edges):
        for kind, density in cfg.density:
            if kind not in PROP_KINDS:
                raise ValueError(f"PropConfig.density: unknown prop kind {kind!r} "
                                 f"(known: {', '.join(PROP_KINDS)})")
            radius = footprint_radius(kind, cfg)
            for _ in range(int(rng.poisson(density * (s1 - s0) / 100.0))):
                for _try in range(cfg.max_tries):
                    s = float(rng.uniform(s0, s1))
                    in_row = kind in ("pedestrian", "bin") and rng.uniform() < cfg.in_row_share
                    if in_row:
                        n_abs = float(rng.uniform(road.lane_width + cfg.lane_margin + radius,
                                                  edge - radius))
                        ground = 0.0
                    else:
                        n_abs = edge + float(rng.uniform(*cfg.sidewalk_offset))
                        ground = road.kerb_height
                    xy = cl.at(s, side * n_abs)
                    spot = Point(float(xy[0]), float(xy[1])).buffer(radius + cfg.clearance)
                    if any(spot.intersects(p) for p in parked) or \
                            any(spot.distance(t) < radius + cfg.clearance for t in taken):
                        continue
                    taken.append(Point(float(xy[0]), float(xy[1])).buffer(radius))
                    road_yaw = float(cl.heading(s)) + (np.pi if side > 0 else 0.0)
                    builder.add(kind, np.array([xy[0], xy[1], ground]),
                                float(rng.uniform(-np.pi, np.pi)), road_yaw)
                    break
    return builder.parts, builder.props


__all__ = ["PropBuilder", "footprint_radius", "place_props"]
