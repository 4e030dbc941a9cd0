"""Procedural colours of the synthetic world: piecewise-constant textures of the 3D point.

Every colour is a function of the surface point only (world road coordinates, facade coordinates
or the car's own frame), never of the pixel, so the left and right images of a stereo pair show the
same texture where they see the same point. Cells are hashed integers (splitmix64), quantised to a
few levels so that PNG compresses the large constant patches well. Shading is Lambertian with a
fixed sun and ambient light, hence view independent.
"""

from __future__ import annotations

import numpy as np

from .cars import BODY, GLASS, RIM, TYRE, LampLayout
from .config import TextureConfig

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)

# Salts that decorrelate the textures of different surfaces.
SALT_ROAD, SALT_KERB, SALT_SIDEWALK, SALT_TERRAIN, SALT_WINDOW = 11, 12, 13, 14, 15
SALT_CAR_GREY, SALT_CAR_ADD = 21, 22


def _splitmix(h: np.ndarray) -> np.ndarray:
    h = h ^ (h >> np.uint64(30))
    h = h * _MIX1
    h = h ^ (h >> np.uint64(27))
    h = h * _MIX2
    return h ^ (h >> np.uint64(31))


def hash01(salt: int | np.ndarray, *cells: np.ndarray) -> np.ndarray:
    """Uniform pseudo-random numbers in [0, 1) from integer cell coordinates and a salt."""
    with np.errstate(over="ignore"):
        h = _splitmix(np.asarray(salt).astype(np.int64).astype(np.uint64) * _GOLDEN + _GOLDEN)
        for c in cells:
            h = _splitmix(h ^ (np.asarray(c).astype(np.int64).astype(np.uint64) * _GOLDEN))
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def levels01(x: np.ndarray, levels: int) -> np.ndarray:
    """Quantise [0, 1) values to ``levels`` evenly spaced values in [0, 1]."""
    return np.floor(x * levels) / max(levels - 1, 1)


def cell_value(salt: int | np.ndarray, coords: list[np.ndarray], sizes: list[float],
               levels: int) -> np.ndarray:
    """Quantised random value of the cell of ``coords`` on a grid of the given cell sizes."""
    return levels01(hash01(salt, *[np.floor(c / s) for c, s in zip(coords, sizes)]), levels)


def lerp(bounds: tuple[float, float], v: np.ndarray) -> np.ndarray:
    """``bounds[0] + (bounds[1] - bounds[0]) * v``."""
    return bounds[0] + (bounds[1] - bounds[0]) * v


def _grey(v: np.ndarray) -> np.ndarray:
    return np.repeat(v[:, None], 3, axis=1)


def road_rgb(s: np.ndarray, n: np.ndarray, lane_width: float, cfg: TextureConfig) -> np.ndarray:
    """Asphalt cells with a dashed centre line and solid lines between lanes and parking strips."""
    grey = lerp(cfg.road_grey, cell_value(SALT_ROAD, [s, n], list(cfg.road_cell), cfg.levels))
    half = 0.5 * cfg.marking_width
    centre = (np.abs(n) < half) & (np.mod(s, cfg.dash_period) < cfg.dash_length)
    edge = np.abs(np.abs(n) - lane_width) < half
    grey = np.where(centre | edge, cfg.marking_grey, grey)
    return _grey(grey)


def kerb_rgb(s: np.ndarray, cfg: TextureConfig) -> np.ndarray:
    return _grey(lerp(cfg.kerb_grey, cell_value(SALT_KERB, [s], [cfg.kerb_cell], cfg.levels)))


def sidewalk_rgb(s: np.ndarray, n: np.ndarray, cfg: TextureConfig) -> np.ndarray:
    v = cell_value(SALT_SIDEWALK, [s, n], [cfg.sidewalk_cell] * 2, cfg.levels)
    return np.array(cfg.sidewalk_rgb, dtype=np.float64) * lerp(cfg.sidewalk_modulation, v)[:, None]


def terrain_rgb(x: np.ndarray, y: np.ndarray, cfg: TextureConfig) -> np.ndarray:
    v = cell_value(SALT_TERRAIN, [x, y], [cfg.terrain_cell] * 2, cfg.levels)
    return np.array(cfg.terrain_rgb, dtype=np.float64) * lerp(cfg.terrain_modulation, v)[:, None]


def facade_rgb(u: np.ndarray, z: np.ndarray, base_rgb: np.ndarray, salt: np.ndarray,
               cfg: TextureConfig) -> np.ndarray:
    """Brick cells in the building's colour with a grid of dark windows above the ground floor.

    ``u`` runs horizontally along the facade, ``z`` is the height; ``base_rgb`` (N, 3) and
    ``salt`` (N,) are per point (from the building that was hit).
    """
    bu, bz = cfg.facade_cell
    v = cell_value(salt, [u, z + 0.5 * bu * np.floor(z / bz)], [bu, bz], cfg.levels)
    rgb = base_rgb * lerp(cfg.facade_modulation, v)[:, None]
    gu, gz = cfg.window_grid
    wu, wz = cfg.window_size
    floor_idx = np.floor(z / gz)
    window = (np.mod(u, gu) < wu) & (np.mod(z, gz) > 0.5 * (gz - wz)) \
        & (np.mod(z, gz) < 0.5 * (gz + wz)) & (floor_idx >= 1)
    shade = cell_value(salt + SALT_WINDOW, [np.floor(u / gu), floor_idx], [1.0, 1.0], cfg.levels)
    glass = np.array(cfg.glass_rgb, dtype=np.float64) * lerp(cfg.window_modulation, shade)[:, None]
    return np.where(window[:, None], glass, rgb)


def car_rgb(local: np.ndarray, material: np.ndarray, paint: np.ndarray, salt: np.ndarray,
            cfg: TextureConfig, normals: np.ndarray | None = None,
            lamps: LampLayout | None = None) -> np.ndarray:
    """Paint / glass / tyre / hub colours modulated by 3D cells in the car's own frame.

    With ``lamps`` (and the car-frame unit ``normals`` of the hit faces), body faces that face
    forwards / backwards are painted as lamps and number plates within the layout's bands.
    """
    cells = [local[:, 0], local[:, 1], local[:, 2]]
    size = [cfg.car_cell] * 3
    v = cell_value(salt + SALT_CAR_GREY, cells, size, cfg.levels) - 0.5
    w = cell_value(salt + SALT_CAR_ADD, cells, size, cfg.levels) - 0.5
    body = paint * (1.0 + cfg.car_modulation * v)[:, None] + (cfg.car_additive * w)[:, None]
    detail = (1.0 + cfg.detail_modulation * v)[:, None]
    glass = np.array(cfg.glass_rgb, dtype=np.float64) * detail
    tyre = np.array(cfg.tyre_rgb, dtype=np.float64) * detail
    out = np.where((material == GLASS)[:, None], glass, body)
    if np.any(material == TYRE):
        out = np.where((material == TYRE)[:, None], tyre, out)
    if np.any(material == RIM):
        out = np.where((material == RIM)[:, None], np.array(cfg.rim_rgb, dtype=np.float64) * detail,
                       out)
    if lamps is not None and normals is not None:
        for mask, rgb in lamp_zones(local, normals, material, lamps, cfg):
            out = np.where(mask[:, None], np.array(rgb, dtype=np.float64) * detail, out)
    return out


def _within(x: np.ndarray, band: tuple[float, float]) -> np.ndarray:
    return (x >= band[0]) & (x <= band[1])


def lamp_zones(local: np.ndarray, normals: np.ndarray, material: np.ndarray, lamps: LampLayout,
               cfg: TextureConfig) -> list[tuple[np.ndarray, tuple[int, int, int]]]:
    """Masks of car-frame points painted as plates, headlamps, indicators and rear lamps (in
    painting order) with their colours."""
    body = material == BODY
    front = body & (normals[:, 0] > cfg.lamp_facing)
    rear = body & (normals[:, 0] < -cfg.lamp_facing)
    z, ay = local[:, 2], np.abs(local[:, 1])
    head = front & _within(z, lamps.head_z) & _within(ay, lamps.head_y)
    return [(front & _within(z, lamps.plate_front_z) & (ay <= lamps.plate_half_width),
             cfg.plate_rgb),
            (rear & _within(z, lamps.plate_rear_z) & (ay <= lamps.plate_half_width), cfg.plate_rgb),
            (head & (ay < lamps.indicator_y), cfg.headlamp_rgb),
            (head & (ay >= lamps.indicator_y), cfg.indicator_rgb),
            (rear & _within(z, lamps.tail_z) & _within(ay, lamps.tail_y), cfg.taillamp_rgb)]


def prop_rgb(points: np.ndarray, base_rgb: np.ndarray, salt: np.ndarray,
             cfg: TextureConfig) -> np.ndarray:
    """A prop part's colour (``base_rgb`` (N, 3), ``salt`` (N,) per point) modulated by 3D
    world cells."""
    v = cell_value(salt, [points[:, 0], points[:, 1], points[:, 2]], [cfg.prop_cell] * 3,
                   cfg.levels)
    return base_rgb * lerp(cfg.prop_modulation, v)[:, None]


def sky_rgb(directions: np.ndarray, cfg: TextureConfig) -> np.ndarray:
    """Sky gradient from the horizon to the zenith by the elevation of the (world) ray direction."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    t = np.clip(d[:, 2] * cfg.sky_gradient, 0.0, 1.0)[:, None]
    return (1 - t) * np.array(cfg.sky_horizon, dtype=np.float64) + t * np.array(cfg.sky_zenith)


def lambert(normals: np.ndarray, cfg: TextureConfig) -> np.ndarray:
    """Two-sided Lambertian shading factor (ambient + diffuse * |n . sun|)."""
    sun = np.asarray(cfg.sun, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    return cfg.ambient + cfg.diffuse * np.abs(normals @ sun)

