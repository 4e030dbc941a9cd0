"""Car-shaped silhouettes of a 3D box: generic body templates, rasterised in a camera.

A box holds no front or back: turned by 180 degrees it is the same box. A car is not: its bonnet
is lower than its roof, its cabin sits towards one end, a pickup's bed is low at the back. A
:class:`BodyTemplate` describes such a body in the box's own normalised coordinates, as a few
convex parts (a lower body, a cabin, wheels), so that projecting it with a box and a camera gives
the silhouette a car of that body type would have there (:func:`rasterise_template`).

Normalised body coordinates: ``z`` from -1 (rear) to +1 (front) along the box's length axis,
``h`` from 0 (the ground) to 1 (the roof) as a fraction of the box height, ``x`` from -1 to +1
across the width. A part's side profile is a convex polygon in ``(z, h)``; its half width is
``w_bottom`` at its lowest point and ``w_top`` at its highest, linearly in between, so every part
is convex and its silhouette is the convex hull of its projected vertices.

The templates (:data:`BODY_TEMPLATES`) are not fitted to any data set: their proportions are those
of common body styles (bonnet about a quarter to a third of the length on saloons, hatchbacks and
SUVs, under a fifth on vans; the roof of a saloon ending above its rear axle, of a hatchback,
estate or SUV near the tail; a pickup's cab in the front half and its bed at beltline height
behind it; the tail taller than the nose on every style); mirrors are left out of the body (they are thin), and the body is a little narrower
than the box, which holds them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .boxes import Box3D
from .camera import NEAR_PLANE, project, transform_points

#: Sub-pixel bits of the polygon rasteriser (OpenCV's ``shift``): vertices at 1/16 px.
RASTER_SHIFT = 4


@dataclass(frozen=True)
class BodyPart:
    """One convex part of a body: side profile ``(z, h)`` (convex polygon, any order) and its
    half width (fraction of the box's half width) at the profile's lowest and highest point."""

    profile: tuple[tuple[float, float], ...]
    w_bottom: float = 0.92
    w_top: float = 0.92

    def vertices(self) -> np.ndarray:
        """``(2 * P, 3)`` normalised ``(x, h, z)`` vertices of the part (both sides)."""
        prof = np.asarray(self.profile, dtype=np.float64)
        h = prof[:, 1]
        lo, hi = float(h.min()), float(h.max())
        frac = (h - lo) / max(hi - lo, 1e-9)
        half = self.w_bottom + (self.w_top - self.w_bottom) * frac
        left = np.stack([half, h, prof[:, 0]], axis=1)
        right = np.stack([-half, h, prof[:, 0]], axis=1)
        return np.concatenate([left, right])


@dataclass(frozen=True)
class BodyTemplate:
    """A named body style as convex parts (see the module docstring for the coordinates)."""

    name: str
    parts: tuple[BodyPart, ...]

    def points(self, box: Box3D) -> list[np.ndarray]:
        """Each part's vertices in the box's frame (metres), the front towards ``box.heading``."""
        half = 0.5 * box.size
        out = []
        for part in self.parts:
            v = part.vertices()
            local = np.stack([v[:, 0] * half[0],            # across the width
                              half[1] - v[:, 1] * box.size[1],  # y down: h = 0 at the bottom
                              v[:, 2] * half[2]], axis=1)   # along the length, +z the front
            out.append(box.centre + local @ box.rotation.T)
        return out


def _body(nose: float, tail: float, belt: float, cabin_bottom: tuple[float, float],
          cabin_top: tuple[float, float], clearance: float = 0.2,
          wheels: tuple[float, float] = (0.62, 0.78)) -> tuple[BodyPart, ...]:
    """Lower body (nose / tail heights at the ends, rising to the beltline under the cabin),
    cabin (trapezoid from ``cabin_bottom`` (rear z, front z) at the beltline to ``cabin_top``
    at the roof) and four wheels (z centred +-``wheels`` mean, radius from the ground to twice
    the clearance)."""
    rear_b, front_b = cabin_bottom
    rear_t, front_t = cabin_top
    lower = BodyPart(((-1.0, clearance), (1.0, clearance), (1.0, nose), (front_b, belt),
                      (rear_b, belt), (-1.0, tail)))
    cabin = BodyPart(((rear_b, belt), (front_b, belt), (front_t, 1.0), (rear_t, 1.0)),
                     w_bottom=0.88, w_top=0.72)
    w0, w1 = wheels
    wheel_parts = tuple(BodyPart(((s * w0, 0.0), (s * w1, 0.0), (s * w1, 2 * clearance),
                                  (s * w0, 2 * clearance)), w_bottom=0.85, w_top=0.85)
                        for s in (-1.0, 1.0))
    return (lower, cabin) + wheel_parts


#: Generic body styles (front at +z). Heights are fractions of the box height, lengths of the
#: half length; see the module docstring for where the proportions come from.
BODY_TEMPLATES: tuple[BodyTemplate, ...] = (
    BodyTemplate("saloon", _body(nose=0.5, tail=0.6, belt=0.6, cabin_bottom=(-0.65, 0.32),
                                 cabin_top=(-0.38, -0.02))),
    BodyTemplate("hatchback", _body(nose=0.5, tail=0.62, belt=0.6, cabin_bottom=(-0.95, 0.35),
                                    cabin_top=(-0.8, 0.0))),
    BodyTemplate("suv", _body(nose=0.62, tail=0.65, belt=0.62, cabin_bottom=(-0.97, 0.45),
                              cabin_top=(-0.92, 0.1))),
    BodyTemplate("van", _body(nose=0.45, tail=0.5, belt=0.5, cabin_bottom=(-1.0, 0.75),
                              cabin_top=(-1.0, 0.5))),
    BodyTemplate("pickup", _body(nose=0.55, tail=0.6, belt=0.62, cabin_bottom=(-0.15, 0.45),
                                 cabin_top=(-0.1, 0.2))),
    BodyTemplate("sports", _body(nose=0.42, tail=0.6, belt=0.55, cabin_bottom=(-0.6, 0.25),
                                 cabin_top=(-0.42, -0.05), clearance=0.15)),
)


def rasterise_template(template: BodyTemplate, box: Box3D, world_to_cam: np.ndarray,
                       K: np.ndarray, roi: tuple[int, int, int, int]) -> np.ndarray | None:
    """Silhouette of ``template`` fitted to ``box`` in a camera, inside ``roi = (x0, y0, x1, y1)``
    (pixel rows / columns ``[y0, y1) x [x0, x1)``). ``box`` is in the frame ``world_to_cam`` maps
    from, at that camera's time. Returns a bool image of the roi, or None when a part reaches
    behind the near plane (the silhouette is then unbounded)."""
    x0, y0, x1, y1 = roi
    canvas = np.zeros((max(y1 - y0, 0), max(x1 - x0, 0)), dtype=np.uint8)
    scale = float(1 << RASTER_SHIFT)
    for pts in template.points(box):
        cam = transform_points(world_to_cam, pts)
        if np.any(cam[:, 2] < NEAR_PLANE):
            return None
        px = project(K, cam) - np.array([x0, y0], dtype=np.float64)
        hull = cv2.convexHull(np.round(px * scale).astype(np.int32))
        cv2.fillConvexPoly(canvas, hull, 1, lineType=cv2.LINE_8, shift=RASTER_SHIFT)
    return canvas.astype(bool)
