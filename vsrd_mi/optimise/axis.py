"""Which horizontal axis of a parked car is its length: a choice among yaw hypotheses.

The stereo initialisation finds a parked car's footprint rectangle from its point cloud, but which
of the rectangle's two axes is the length it can only tell when the cloud shows more than a car's
width along one of them; otherwise it takes the axis nearer the road (the direction of travel). A
short car standing across the road, or angled at 45 degrees, then starts 90 degrees off, and the
box optimisation, whose projection loss is blind to a turn that swaps a box's length and width in
some views, ends in a local minimum.

The masks of the ~16 frames around the target tell the axes apart: a box standing the wrong way
projects to rectangles of the wrong widths as the camera drives past. For every parked instance,
:func:`choose_yaw` fits a box to the instance's mask boxes (the optimiser's projection loss in its
plain form: smooth L1 of the projected box corners against the mask box, one-sided on the sides an
occluder may cut short, plus the initialisation anchor on the centre) for each yaw hypothesis
(the initial yaw and the initial yaw turned by 90 degrees; for cars beyond
``AxisConfig.road_hypotheses_beyond`` also the road's direction and its normal, since there the
cloud's rectangle itself is uncertain), and keeps the initial yaw unless another hypothesis fits
the mask boxes clearly better (``AxisConfig.switch_ratio``) and a car body in its box overlaps
the masks better too (``AxisConfig.min_silhouette_gain``: the mask boxes alone can be matched by
a box turned the wrong way, the masks' shapes less so). Where the initial axis was only the road
prior's (the cloud did not show the length), the initial yaw is no evidence and the hypothesis
that fits the mask boxes best is taken: there the car-body silhouettes are no guide (a car seen
end-on overlaps a body standing either way about equally; on the development set they vetoed 5
of 14 such cars' right turns and saved none; docs/accuracy.md, "Length axis").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

from ..data.observations import Observations
from ..geometry.boxes import CORNER_SIGNS, Box3D, wrap_angle
from ..geometry.camera import NEAR_PLANE, image_bounds
from ..geometry.silhouettes import BODY_TEMPLATES, BodyTemplate, rasterise_template
from .config import AxisConfig

#: Huber transition (px) of the fit's residuals, the optimiser's default.
HUBER_BETA_PX = 1.0
#: Residuals are measured in units of the mask box's diagonal times this (px): a 100 px mask box
#: keeps its pixels, a 400 px one counts a quarter per pixel.
REFERENCE_DIAGONAL_PX = 100.0
#: Pixels around a mask box within which :func:`silhouette_iou` compares silhouettes.
SILHOUETTE_MARGIN_PX = 20
#: Cost evaluations of one hypothesis's fit (Powell's method).
FIT_EVALUATIONS = 300
#: Box sizes the fit may reach: width (x, mirrors included) and length (z) in metres, those of
#: cars, pickups and vans: a box turned the wrong way cannot pass a car's length off as its width.
WIDTH_RANGE = (1.4, 2.5)
LENGTH_RANGE = (3.0, 6.5)
HEIGHT_RANGE = (1.1, 2.3)


@dataclass(frozen=True)
class AxisChoice:
    """The yaw kept for one box and what the hypotheses cost."""

    yaw: float
    #: Hypothesis yaws and their fitted costs, the initial yaw first.
    hypotheses: tuple[float, ...]
    costs: tuple[float, ...]
    switched: bool


def _huber(x: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    return np.where(ax < HUBER_BETA_PX, 0.5 * x * x / HUBER_BETA_PX, ax - 0.5 * HUBER_BETA_PX)


def projected_rectangles(box: Box3D, world_to_cam: np.ndarray, K: np.ndarray,
                         bounds: np.ndarray) -> np.ndarray:
    """``(L, 4)`` rectangles of the 8 box corners projected by ``L`` cameras (``world_to_cam``
    ``(L, 4, 4)``), clipped to ``bounds``; a camera with a corner behind its near plane gets NaN."""
    corners = box.centre + (CORNER_SIGNS * (0.5 * box.size)) @ box.rotation.T       # (8, 3)
    cam = np.einsum("lij,kj->lki", world_to_cam[:, :3, :3], corners) + world_to_cam[:, None, :3, 3]
    uvw = cam @ K.T
    uv = uvw[..., :2] / uvw[..., 2:3]
    rect = np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)
    rect = np.clip(rect, bounds[[0, 1, 0, 1]], bounds[[2, 3, 2, 3]])
    rect[np.any(cam[..., 2] < NEAR_PLANE, axis=1)] = np.nan
    return rect


def fit_cost(box: Box3D, yaw: float, world_to_cam: np.ndarray, K: np.ndarray, bounds: np.ndarray,
             target: np.ndarray, open_sides: np.ndarray, anchor: float) -> tuple[float, Box3D]:
    """Least cost of a box with ``yaw`` (centre x / z, width, length and height free; the bottom's
    level and the rest from ``box``) against
    the mask boxes ``target`` (L, 4), and that box. Cost: mean over the cameras of the four sides'
    smooth L1 (one-sided where ``open_sides``, in units of the mask box's size) plus ``anchor``
    times the L1 distance of the centre from ``box``'s."""
    bottom = box.centre[1] + 0.5 * box.size[1]  # y points down: the box stands on this level

    def make(p: np.ndarray) -> Box3D:
        w = float(np.exp(np.clip(p[2], *np.log(WIDTH_RANGE))))
        length = float(np.exp(np.clip(p[3], *np.log(LENGTH_RANGE))))
        h = float(np.exp(np.clip(p[4], *np.log(HEIGHT_RANGE))))
        return Box3D((p[0], bottom - 0.5 * h, p[1]), (w, h, length), yaw, box.velocity, box.dynamic,
                     box.instance_id)

    # each camera's residuals in units of its mask box's diagonal: a near view's pixels must not
    # outweigh the far views (the pixel loss of the optimiser is scale-free in the same way per
    # lane only through its DIoU term)
    scale = np.hypot(target[:, 2] - target[:, 0], target[:, 3] - target[:, 1])[:, None] / REFERENCE_DIAGONAL_PX

    def cost(p: np.ndarray) -> float:
        rect = projected_rectangles(make(p), world_to_cam, K, bounds)
        e = np.nan_to_num((rect - target) / scale, nan=1e3)
        e[:, :2] = np.where(open_sides[:, :2], np.maximum(e[:, :2], 0.0), e[:, :2])
        e[:, 2:] = np.where(open_sides[:, 2:], np.minimum(e[:, 2:], 0.0), e[:, 2:])
        shift = abs(p[0] - box.centre[0]) + abs(p[1] - box.centre[2])
        return float(_huber(e).sum(axis=1).mean() + anchor * shift)

    # every hypothesis starts from the box's extents with its longer horizontal one as the length
    horizontal = sorted((box.size[0], box.size[2]))
    size = np.clip((horizontal[0], box.size[1], horizontal[1]), (WIDTH_RANGE[0], HEIGHT_RANGE[0], LENGTH_RANGE[0]),
                   (WIDTH_RANGE[1], HEIGHT_RANGE[1], LENGTH_RANGE[1]))
    p0 = np.array([box.centre[0], box.centre[2], np.log(size[0]), np.log(size[2]), np.log(size[1])])
    res = minimize(cost, p0, method="Powell", options={"maxfev": FIT_EVALUATIONS, "xtol": 1e-3})
    return float(res.fun), make(res.x)


def hypotheses(yaw: float, road: bool = True) -> list[float]:
    """The initial yaw, it turned by 90 degrees, and (``road``) the optimisation frame's forward
    direction (the road, along which the ego drives) and its normal; duplicates (mod 180) dropped."""
    out: list[float] = []
    for y in (yaw, yaw + 0.5 * np.pi) + ((0.0, 0.5 * np.pi) if road else ()):
        y = float(wrap_angle(y))
        if all(abs(wrap_angle(2.0 * (y - o))) > 1e-6 for o in out):
            out.append(y)
    return out


def choose_yaw(box: Box3D, n: int, obs: Observations, cfg: AxisConfig, anchor: float,
               axis_seen: bool = True) -> AxisChoice:
    """The yaw hypothesis of box ``n`` (instance ``n`` of ``obs``) the masks support (see the
    module docstring): the initial yaw unless another costs less than ``cfg.switch_ratio`` of it
    and its car body overlaps the masks better by ``cfg.min_silhouette_gain``; when the initial
    axis was not ``axis_seen`` but the road prior's, the cheapest hypothesis."""
    views = np.flatnonzero(obs.visible[:, n])
    ys = hypotheses(box.yaw, road=float(np.linalg.norm(box.centre[[0, 2]])) > cfg.road_hypotheses_beyond)
    if box.dynamic or len(views) < cfg.min_views:
        return AxisChoice(box.yaw, tuple(ys), (), False)
    w2c = np.linalg.inv(obs.cam_to_opt[views])
    bounds = image_bounds(obs.image_size)
    fits = [fit_cost(box, y, w2c, obs.K[0], bounds, obs.boxes2d[views, n], obs.open_sides[views, n], anchor)
            for y in ys]
    costs = [c for c, _ in fits]
    best = int(np.argmin(costs))
    if not axis_seen:  # the initial axis is only the road prior's: the best fit wins
        switched = best != 0
    else:
        switched = (best != 0 and costs[best] < cfg.switch_ratio * costs[0]
                    and silhouette_iou(fits[best][1], n, obs, views)
                    > silhouette_iou(fits[0][1], n, obs, views) + cfg.min_silhouette_gain)
    return AxisChoice(ys[best] if switched else box.yaw, tuple(ys), tuple(costs), switched)


def silhouette_iou(box: Box3D, n: int, obs: Observations, views: np.ndarray,
                   templates: tuple[BodyTemplate, ...] = BODY_TEMPLATES) -> float:
    """How well ``box`` explains instance ``n``'s masks in ``views``: the mean IoU over the views
    of the mask and the silhouette of a car body in the box (:mod:`vsrd_mi.geometry.silhouettes`),
    for the body style and front end that match best, leaving out the other instances' masks
    (they may hide the car). A box's own outline is not a car's: a box turned the wrong way can
    match the masks' outlines as well as the right one, a car body less so."""
    W, H = obs.image_size
    ious = np.zeros((len(templates), 2))
    count = 0
    for f in views:
        w2c = np.linalg.inv(obs.cam_to_opt[f])
        rect = np.concatenate([obs.boxes2d[f, n, :2] - SILHOUETTE_MARGIN_PX, obs.boxes2d[f, n, 2:] + SILHOUETTE_MARGIN_PX])
        x0, y0 = (int(max(v, 0)) for v in np.floor(rect[:2]))
        x1, y1 = int(min(np.ceil(rect[2]), W)), int(min(np.ceil(rect[3]), H))
        mask = obs.masks[f, n, y0:y1, x0:x1]
        care = ~(np.delete(obs.masks[f], n, axis=0)[:, y0:y1, x0:x1].any(axis=0) & ~mask)
        at = box.at_offset(float(obs.dt[f]))
        sils = [[rasterise_template(t, replace(at, yaw=at.yaw + turn), w2c, obs.K[f], (x0, y0, x1, y1))
                 for turn in (0.0, np.pi)] for t in templates]
        if any(s is None for row in sils for s in row):
            continue
        count += 1
        for i, row in enumerate(sils):
            for j, sil in enumerate(row):
                union = np.count_nonzero((sil | mask) & care)
                ious[i, j] += np.count_nonzero(sil & mask & care) / union if union else 0.0
    return float(ious.max() / count) if count else 0.0


def choose_yaws(boxes: list[Box3D], obs: Observations, cfg: AxisConfig, anchor: float,
                axis_seen: list[bool] | None = None) -> list[AxisChoice]:
    """:func:`choose_yaw` for the initial box of every instance of ``obs`` (box k is instance k);
    ``axis_seen[k]``: whether box k's axis came from evidence (default: all did)."""
    if not cfg.enabled:
        return [AxisChoice(b.yaw, (b.yaw,), (), False) for b in boxes]
    seen = [True] * len(boxes) if axis_seen is None else axis_seen
    return [choose_yaw(b, k, obs, cfg, anchor, s) for k, (b, s) in enumerate(zip(boxes, seen))]


__all__ = ["AxisChoice", "choose_yaw", "choose_yaws", "fit_cost", "hypotheses", "projected_rectangles"]
