"""Loss terms of the box optimisation (paper eq. 13-16, docs/method.md §3-4), in Dr.Jit.

Every function is differentiable and works on flat Dr.Jit arrays; the matching, ray sampling
and bookkeeping around them live in :mod:`vsrd_mi.optimise.optimiser`.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from vsrd_plugins.sdf import DecodedBoxes, InstanceField, box_sdf_local

from ..geometry import boxes2d
from ..geometry.boxes import CORNER_SIGNS, Box3D
from ..geometry.camera import NEAR_PLANE, footprint
from ..geometry.surface import footprint_ray_residuals, quantile_soft_l1, range_quantile
from ..geometry.vehicle_sizes import tight_width, typical_length
from ..geometry.xp import drjit_namespace
from .config import MAX_PART_FRACTION, CarProfile


def to_float(values) -> mi.Float:
    """A Dr.Jit Float holding a copy of NumPy ``values`` in Dr.Jit-owned (aligned) memory.

    ``mi.Float(ndarray)`` can use the NumPy buffer in place; its alignment then varies from call to
    call and becomes part of the kernel hash, so every step recompiles (measured: ~17 kernel
    misses and ~4 s of LLVM time per step; ``dr.copy`` did not always help). Building from a
    Python list always allocates Dr.Jit memory.
    """
    return mi.Float(np.asarray(values, dtype=np.float32).ravel().tolist())


def to_uint(values) -> mi.UInt32:
    """UInt32 counterpart of :func:`to_float`."""
    return mi.UInt32(np.asarray(values, dtype=np.int64).ravel().tolist())


def huber(x, beta: float):
    """Smooth L1 with transition ``beta``: ``0.5 x^2 / beta`` inside, ``|x| - beta / 2`` outside."""
    ax = dr.abs(x)
    return dr.select(ax < beta, 0.5 * x * x / beta, ax - 0.5 * beta)


def binary_cross_entropy(p, y, eps: float):
    """Per-element BCE of predictions ``p`` (clamped to ``[eps, 1 - eps]``) against targets ``y``."""
    p = dr.clip(p, eps, 1.0 - eps)
    return -(y * dr.log(p) + (1.0 - y) * dr.log(1.0 - p))


def mean(x) -> mi.Float:
    n = dr.width(x)
    return dr.sum(x) / max(n, 1)


class ProjectionLanes:
    """The (frame, box) pairs supervised by the projection loss, as flat lane arrays.

    Built from NumPy: ``box`` (L,) box index, ``dt`` (L,) frame offsets, ``world_to_cam`` (L, 4, 4)
    optimisation frame -> camera, ``target`` (L, 4) mask boxes, and optionally ``open_sides``
    (L, 4) bool: the sides of a mask box that an occluder or the image edge may cut short
    (:func:`vsrd_mi.data.masks.open_sides`). All lanes share intrinsics ``K`` and image ``bounds``.
    """

    #: The Dr.Jit arrays (``DRJIT_STRUCT``: a frozen function that takes this object reads them
    #: as inputs; ``K`` and ``bounds`` enter its kernels as constants).
    DRJIT_STRUCT = {"box": mi.UInt32, "dt": mi.Float, "rot": list, "trans": list, "target": list,
                    "open": list, "closed": mi.Float}

    def __init__(self, box: np.ndarray, dt: np.ndarray, world_to_cam: np.ndarray,
                 target: np.ndarray, K: np.ndarray, bounds: np.ndarray,
                 open_sides: np.ndarray | None = None):
        self.count = len(box)
        self.box = to_uint(box)
        self.dt = to_float(dt)
        self.rot = [[to_float(world_to_cam[:, i, j]) for j in range(3)] for i in range(3)]
        self.trans = [to_float(world_to_cam[:, i, 3]) for i in range(3)]
        self.target = [to_float(target[:, i]) for i in range(4)]
        opened = np.zeros((self.count, 4), bool) if open_sides is None else np.asarray(open_sides, bool)
        #: Per side, 1 where the side is open (a float so that no mask type enters the kernels).
        self.open = [to_float(opened[:, i]) for i in range(4)]
        #: 1 on lanes whose mask box is whole (no open side): the DIoU term applies to those.
        self.closed = to_float(~opened.any(axis=1))
        self.K = np.asarray(K, dtype=np.float64)
        self.bounds = tuple(float(b) for b in bounds)


@dataclass(frozen=True)
class LaneBoxes:
    """Boxes gathered per lane (optimisation frame, moved by ``dynamic * v * dt``): centre and
    half extents (3 arrays each) and the yaw's ``cos`` / ``sin``."""

    centre: tuple
    half: tuple
    cos: mi.Float
    sin: mi.Float

    @staticmethod
    def gather(dec: DecodedBoxes, box: mi.UInt32, dt: mi.Float) -> "LaneBoxes":
        def g(a):
            return dr.gather(mi.Float, a, box)

        m = g(dec.dynamic) * dt
        return LaneBoxes(tuple(g(dec.centre[j]) + m * g(dec.velocity[j]) for j in range(3)),
                         tuple(g(h) for h in dec.half), g(dec.cos), g(dec.sin))


def _cuts(amount) -> bool:
    """Whether ``amount`` (metres: a Python float, or a per-lane Dr.Jit array) may cut a part."""
    return not isinstance(amount, (int, float)) or amount > 0


def box_corners(boxes: LaneBoxes, shorten: float | mi.Float = 0.0, raise_bottom: float = 0.0,
                narrow: float | mi.Float = 0.0, keep_length: float = 1.0, keep_height: float = 1.0) -> list[tuple]:
    """The 8 corners of gathered ``boxes``.

    ``shorten``, ``narrow`` (metres, one value or one per lane) and ``raise_bottom`` (metres)
    give the corners of a part of each box
    instead: ``shorten`` off each end along the length, ``narrow`` off each side along the
    width, the bottom face raised by ``raise_bottom`` (the optimisation frame's y points down),
    each capped at :data:`MAX_PART_FRACTION` of the extent. ``keep_length`` (fraction, centred)
    keeps that share of the length, ``keep_height`` lowers the top face to that fraction of the
    height above the box's bottom; the bottom is raised by at most :data:`MAX_PART_FRACTION` of
    the height, so a part keeps ``keep_height - MAX_PART_FRACTION`` of it at least.
    """
    centre, half = list(boxes.centre), list(boxes.half)
    if _cuts(shorten):
        half[2] = half[2] - dr.minimum(shorten, 2.0 * MAX_PART_FRACTION * half[2])
    if keep_length < 1.0:
        half[2] = half[2] * keep_length
    if _cuts(narrow):
        half[0] = half[0] - dr.minimum(narrow, 2.0 * MAX_PART_FRACTION * half[0])
    if keep_height < 1.0:
        drop = (1.0 - keep_height) * half[1]  # half of the top's drop: the centre moves down by it
        half[1] = half[1] - drop
        centre[1] = centre[1] + drop
    if raise_bottom > 0:
        lift = 0.5 * dr.minimum(raise_bottom, 2.0 * MAX_PART_FRACTION * boxes.half[1])
        half[1] = half[1] - lift
        centre[1] = centre[1] - lift
    c, s = boxes.cos, boxes.sin
    corners = []
    for sx, sy, sz in CORNER_SIGNS.tolist():  # Python floats: NumPy scalars would promote to Float64
        lx, ly, lz = sx * half[0], sy * half[1], sz * half[2]
        corners.append((centre[0] + c * lx + s * lz, centre[1] + ly, centre[2] - s * lx + c * lz))
    return corners


def _footprint(corners: list[tuple], lanes: ProjectionLanes):
    R, t = lanes.rot, lanes.trans
    cam = [tuple(R[i][0] * p[0] + R[i][1] * p[1] + R[i][2] * p[2] + t[i] for i in range(3))
           for p in corners]
    return footprint(cam, lanes.K, lanes.bounds, NEAR_PLANE, xp=drjit_namespace())


def projected_boxes(dec: DecodedBoxes, lanes: ProjectionLanes, profile: CarProfile | None = None,
                    corner: mi.Float | None = None):
    """Differentiable 2D footprints ``(x1, y1, x2, y2, valid)`` of the lanes' boxes.

    Without a ``profile`` (or with a zero one) the footprint of the 8 box corners (the paper).
    With one, the footprint of the car the box bounds, as parts: the body (``profile.mirror``
    narrower on each side than the box, which holds the mirrors) above
    ``profile.clearance`` over the full length, its plan's corners cut by ``profile.corner``
    (two crossed boxes, one ``corner`` narrower on each side, one ``corner`` shorter at each
    end), and a part reaching the ground over the length less ``profile.overhang`` of it at each end,
    where the wheels meet it; with ``profile.roof < 1`` these parts end at ``profile.waist`` of the
    height and a roof part (``profile.roof`` of the length, centred, as narrow as the octagon's
    cut ends so that it lies inside the body's plan) reaches the box's top (see
    :class:`~vsrd_mi.optimise.config.CarProfile`). A car's mask box is the projection of the
    car, not of its box: the box's bottom corners at the ends enclose empty space under the
    bumpers, which project below the mask in every view that sees an end of the car, and its top
    corners at the ends enclose the space over the bonnet and the boot or bed.
    ``corner`` (N, metres), where given, is each box's own plan-corner cut (fitted with the box,
    :class:`~vsrd_mi.optimise.parameters.CornerRange`) in place of ``profile.corner``. A cut is
    at most :data:`MAX_PART_FRACTION` of the box's smaller extent less the mirror span (the body's
    half width must keep some of its length: 0.42 m for a 1.8 m wide box).
    """
    boxes = LaneBoxes.gather(dec, lanes.box, lanes.dt)  # once: every part is built from it
    if profile is None or not profile.enabled:
        return _footprint(box_corners(boxes), lanes)
    body = profile.mirror  # the box holds the mirrors, the body is that much narrower per side
    waist = profile.waist if profile.roof < 1.0 else 1.0  # outside the roof the body ends lower
    cut = profile.corner if corner is None else dr.gather(mi.Float, corner, lanes.box)
    if _cuts(cut):  # the body's plan: an octagon, the union of two crossed boxes
        # one cut for both: box_corners caps each part's narrowing / shortening at
        # MAX_PART_FRACTION of the extent, and a cut capped on one side only is no octagon
        cap = 2.0 * MAX_PART_FRACTION * dr.minimum(boxes.half[0], boxes.half[2]) - body
        cut = dr.minimum(cut, dr.maximum(cap, 0.0))
        parts = [box_corners(boxes, raise_bottom=profile.clearance, narrow=body + cut, keep_height=waist),
                 box_corners(boxes, raise_bottom=profile.clearance, shorten=cut, narrow=body,
                             keep_height=waist)]
    else:
        parts = [box_corners(boxes, raise_bottom=profile.clearance, narrow=body, keep_height=waist)]
    if profile.clearance > 0:  # below the bumpers only the wheels, between the overhangs
        parts.append(box_corners(boxes, keep_length=1.0 - 2.0 * profile.overhang, narrow=body, keep_height=waist))
    if profile.roof < 1.0:  # the full height only over the roof, centred on the box
        parts.append(box_corners(boxes, raise_bottom=profile.clearance, narrow=body + cut,
                                 keep_length=profile.roof))
    x1, y1, x2, y2, valid = _footprint(parts[0], lanes)
    for corners in parts[1:]:
        p = _footprint(corners, lanes)
        x1, y1 = dr.minimum(x1, p[0]), dr.minimum(y1, p[1])
        x2, y2, valid = dr.maximum(x2, p[2]), dr.maximum(y2, p[3]), valid | p[4]
    return x1, y1, x2, y2, valid


def projection_loss(dec: DecodedBoxes, lanes: ProjectionLanes, beta: float,
                    w_huber: float, w_diou: float, containment: bool = False,
                    excess: float = 0.0, profile: CarProfile | None = None,
                    corner: mi.Float | None = None) -> mi.Float:
    """Mean over lanes of :func:`projection_lane_loss`."""
    if lanes.count == 0:
        return mi.Float(0.0)
    return mean(projection_lane_loss(dec, lanes, beta, w_huber, w_diou, containment, excess, profile, corner))


def projection_lane_loss(dec: DecodedBoxes, lanes: ProjectionLanes, beta: float,
                         w_huber: float, w_diou: float, containment: bool = False,
                         excess: float = 0.0, profile: CarProfile | None = None,
                         corner: mi.Float | None = None) -> mi.Float:
    """Per lane: ``w_huber * sum_4 Huber(e_i) + w_diou * (1 - DIoU)``.

    ``symmetric`` (the paper, ``containment=False``): ``e = pred - mask box`` per coordinate.
    ``containment=True``: the part of the mask box that sticks out of the projected box counts
    fully, ``u = max(0, x1p - x1m), max(0, y1p - y1m), max(0, x2m - x2p), max(0, y2m - y2p)``,
    and the part of the projected box outside the mask box (``o``, the same with the signs
    swapped) with weight ``excess``: ``Huber(u_i) + excess * Huber(o_i)`` (``excess = 1`` is the
    symmetric loss). A box that contains the object projects to a rectangle containing the
    mask's box, but not onto it (an object is not a box: its silhouette is smaller than its
    box's footprint), so the symmetric loss pulls boxes smaller -- and, for moving cars whose
    depth trades off against velocity, farther away; with ``excess < 1`` the mask boxes bound
    the box from inside and ``excess`` only tightens it. ``profile``, ``corner``: see
    :func:`projected_boxes`.
    """
    x1, y1, x2, y2, _ = projected_boxes(dec, lanes, profile, corner)
    pred = (x1, y1, x2, y2)
    tgt = lanes.target
    if containment:
        # positive where the mask box sticks out of the projected box (min sides: pred > mask)
        out = [x1 - tgt[0], y1 - tgt[1], tgt[2] - x2, tgt[3] - y2]
        h = mi.Float(0.0)
        for e in out:
            h = h + huber(dr.maximum(e, 0.0), beta)
            if excess > 0:
                h = h + excess * huber(dr.maximum(-e, 0.0), beta)
    else:
        h = mi.Float(0.0)
        for i in range(4):
            e = pred[i] - tgt[i]
            # the projection falls short of an open side when it lies inside it: e > 0 at the
            # min sides (x1, y1), e < 0 at the max sides (x2, y2)
            inside = dr.maximum(e, 0.0) if i < 2 else dr.minimum(e, 0.0)
            h = h + huber(dr.select(lanes.open[i] > 0.5, inside, e), beta)
    total = w_huber * h
    if w_diou > 0:
        total = total + w_diou * lanes.closed * (1.0 - boxes2d.diou(pred, tgt, xp=dr))
    return total


def silhouette_loss(labels: list, targets: list, eps: float) -> mi.Float:
    """Mean per-instance BCE of rendered labels against target masks (docs/method.md §3)."""
    total = mi.Float(0.0)
    for p, y in zip(labels, targets):
        total = total + mean(binary_cross_entropy(p, y, eps))
    return total / max(len(labels), 1)


def seen_face_normals(boxes: list[Box3D], camera: np.ndarray | None = None) -> np.ndarray:
    """Outward horizontal normals of the side and end faces of each box that ``camera`` sees.

    ``camera`` (3,) is a point in the boxes' frame, by default its origin (the target camera of
    the optimisation frame). Returns (N, 4): ``(side_x, side_z, end_x, end_z)``, the unit normal
    in the x-z plane of the side face (width axis) and of the end face (length axis) facing the
    camera, or zeros for an axis whose two faces the camera cannot see (it lies within the box's
    extent along that axis).
    """
    cam = np.zeros(3) if camera is None else np.asarray(camera, dtype=np.float64)
    normals = np.zeros((len(boxes), 4))
    for i, b in enumerate(boxes):
        local = b.rotation.T @ (cam - b.centre)   # the camera in box coordinates (x width, z length)
        for axis in (0, 2):   # normals' columns 0:2 hold the side (local x), 2:4 the end (local z)
            if abs(local[axis]) > 0.5 * b.size[axis]:
                normals[i, axis:axis + 2] = np.sign(local[axis]) * b.rotation[[0, 2], axis]
    return normals


def face_anchor_point(centre: list, half: list, normals: list, side_inset) -> tuple:
    """``(x, z)`` of the point an init anchor holds: ``centre`` moved by the half extents onto
    the faces whose outward ``normals`` ``(side_x, side_z, end_x, end_z)`` are given (zero
    normals leave that axis at the centre), the side face taken ``side_inset`` metres inside the
    box. Arithmetic only: NumPy arrays and Dr.Jit arrays alike (the one formula of both)."""
    side = half[0] - side_inset
    return (centre[0] + normals[0] * side + normals[2] * half[2],
            centre[2] + normals[1] * side + normals[3] * half[2])


class InitAnchor:
    """The init regulariser's constants as Dr.Jit arrays, converted once per optimisation:
    initial centres ``centre_init`` (N, 3), velocities ``velocity_init`` (N, 3) or None (no
    velocity term), the mask of boxes whose velocity counts ``velocity_mask`` (N,) and weights
    ``box_weights`` (N,) or None (all 1). :meth:`loss` is :func:`init_loss`.

    With ``face_normals`` (N, 4; :func:`seen_face_normals`) the anchor holds, horizontally, the
    point of each box on the faces those normals name instead of its centre
    (:func:`face_anchor_point`): initially ``init_half`` (N, 3) from the centre, at the faces as
    the stereo cloud placed them, and during the optimisation ``side_inset`` metres nearer the
    centre on the side face. A box then grows away from the faces its cloud measured; boxes
    with zero normals keep the plain centre anchor.
    """

    DRJIT_STRUCT = {"centre": list, "w": mi.Float, "velocity": object, "mask": object, "normals": object}

    def __init__(self, centre_init: np.ndarray, velocity_init: np.ndarray | None,
                 velocity_mask: np.ndarray | None, box_weights: np.ndarray | None = None,
                 face_normals: np.ndarray | None = None, init_half: np.ndarray | None = None,
                 side_inset: float = 0.0):
        n = self.count = len(centre_init)
        target = np.array(centre_init, dtype=np.float64).reshape(n, 3)
        self.normals, self.side_inset = None, float(side_inset)
        if face_normals is not None:
            if init_half is None:
                raise ValueError("InitAnchor: face_normals need init_half, the initial half extents")
            normals, half = np.asarray(face_normals, dtype=np.float64), np.asarray(init_half, dtype=np.float64)
            target[:, 0], target[:, 2] = face_anchor_point(list(target.T), list(half.T), list(normals.T), 0.0)
            self.normals = [to_float(normals[:, j]) for j in range(4)]
        self.centre = [to_float(target[:, j]) for j in range(3)]
        self.w = to_float(np.ones(n) if box_weights is None else box_weights)
        self.velocity = self.mask = None
        if velocity_init is not None:
            self.velocity = [to_float(np.asarray(velocity_init)[:, j]) for j in range(3)]
            self.mask = to_float(np.ones(n) if velocity_mask is None else velocity_mask)

    def loss(self, dec: DecodedBoxes) -> mi.Float:
        """``sum_n w_n (|p_n - p_init|_1 + m_n |v_n - v_init|_1) / N``, ``p`` the centre or,
        with face normals, the face point (horizontally) and the centre's height."""
        point = list(dec.centre)
        if self.normals is not None:
            point[0], point[2] = face_anchor_point(point, dec.half, self.normals, self.side_inset)
        per_box = dr.zeros(mi.Float, self.count)
        for j in range(3):
            per_box = per_box + dr.abs(point[j] - self.centre[j])
            if self.velocity is not None:
                per_box = per_box + self.mask * dr.abs(dec.velocity[j] - self.velocity[j])
        return dr.sum(self.w * per_box) / max(self.count, 1)


def init_loss(dec: DecodedBoxes, centre_init: np.ndarray, velocity_init: np.ndarray | None,
              velocity_mask: np.ndarray | None, box_weights: np.ndarray | None = None) -> mi.Float:
    """``sum_n w_n (|l_n - l_init|_1 + |v_n - v_init|_1) / N`` (velocity only where
    ``velocity_mask``); ``box_weights`` ``w_n`` default to 1. An optimisation builds the
    :class:`InitAnchor` once instead."""
    return InitAnchor(centre_init, velocity_init, velocity_mask, box_weights).loss(dec)


class ShapePrior:
    """The size / yaw prior's constants as Dr.Jit arrays, converted once per optimisation:
    initial sizes ``size_init`` (N, 3) (w, h, l), yaws ``yaw_init`` (N,), and weights ``w_size``,
    ``w_yaw`` (scalars or per box). :meth:`loss` is :func:`shape_prior_loss`."""

    DRJIT_STRUCT = {"w_size": object, "size": list, "w_yaw": object, "cos": mi.Float, "sin": mi.Float}

    def __init__(self, size_init: np.ndarray, yaw_init: np.ndarray, w_size, w_yaw):
        n = self.count = len(size_init)
        ws = np.broadcast_to(np.asarray(w_size, dtype=np.float64), (n,))
        wy = np.broadcast_to(np.asarray(w_yaw, dtype=np.float64), (n,))
        yaw = np.asarray(yaw_init, dtype=np.float64)
        self.w_size = to_float(ws) if np.any(ws > 0) else None
        self.size = [to_float(np.asarray(size_init)[:, j]) for j in range(3)]
        self.w_yaw = to_float(wy) if np.any(wy > 0) else None
        self.cos, self.sin = to_float(np.cos(yaw)), to_float(np.sin(yaw))

    @property
    def active(self) -> bool:
        """Whether any box has a non-zero size or yaw weight."""
        return self.w_size is not None or self.w_yaw is not None

    def loss(self, dec: DecodedBoxes) -> mi.Float:
        """``sum_n (w_size_n |size_n - size_init_n|_1 + w_yaw_n sin^2(yaw_n - yaw_init_n)) / N``."""
        per_box = dr.zeros(mi.Float, self.count)
        if self.w_size is not None:
            for j in range(3):
                per_box = per_box + self.w_size * dr.abs(2.0 * dec.half[j] - self.size[j])
        if self.w_yaw is not None:
            sin_d = dec.sin * self.cos - dec.cos * self.sin
            per_box = per_box + self.w_yaw * sin_d * sin_d
        return dr.sum(per_box) / max(self.count, 1)


class _CataloguePrior:
    """Per-box weights ``weights`` (N,) of a size prior from the vehicle catalogue."""

    DRJIT_STRUCT = {"w": mi.Float}

    def __init__(self, weights: np.ndarray):
        self.count = len(weights)
        self.w = to_float(np.asarray(weights, dtype=np.float64))


class WidthPrior(_CataloguePrior):
    """Width of each box drawn towards the width real vehicles of its length and height have
    (:func:`vsrd_mi.geometry.vehicle_sizes.tight_width`), with per-box weights ``weights`` (N,).

    The masks fix a car's length and height but leave its width free to trade against its yaw,
    length and range (docs/accuracy.md, "Widths"); this term settles that trade. The length and
    height enter detached: the prior moves the width only, never the extents the masks measure.
    """

    def loss(self, dec: DecodedBoxes) -> mi.Float:
        """``sum_n w_n |width_n - tight_width(length_n, height_n)| / N`` (metres)."""
        expected = tight_width(2.0 * dr.detach(dec.half[2]), 2.0 * dr.detach(dec.half[1]))
        return dr.sum(self.w * dr.abs(2.0 * dec.half[0] - expected)) / max(self.count, 1)


class LengthPrior(_CataloguePrior):
    """Length of each box drawn towards the length real vehicles of its body width and height
    have (:func:`vsrd_mi.geometry.vehicle_sizes.typical_length`), with per-box weights
    ``weights`` (N,).

    For the boxes whose length no view measures (a car seen end-on in every view), whose width
    and height the masks do measure; the width and height enter detached, so the prior moves the
    length only. A box holds the mirrors, ``mirror`` metres a side (``CarProfile.mirror``: the
    projection loss fits the body, that much narrower a side, to the masks), and the plane takes
    the body width, the box width less twice that. A box under this prior takes
    no :class:`WidthPrior` (the two planes together would move its width and length round each
    other).
    """

    def __init__(self, weights: np.ndarray, *, mirror: float):
        super().__init__(weights)
        if not mirror >= 0:
            raise ValueError(f"LengthPrior: mirror must be >= 0 m, got {mirror}")
        self.mirror = float(mirror)

    def loss(self, dec: DecodedBoxes) -> mi.Float:
        """``sum_n w_n |length_n - typical_length(width_n - 2 mirror, height_n)| / N`` (metres)."""
        body_width = 2.0 * (dr.detach(dec.half[0]) - self.mirror)
        expected = typical_length(body_width, 2.0 * dr.detach(dec.half[1]))
        return dr.sum(self.w * dr.abs(2.0 * dec.half[2] - expected)) / max(self.count, 1)


class VisibleSurface:
    """Parked boxes held on the visible surface their stereo points show.

    The mask boxes let a box trade its range against its size (a box nearer and smaller projects
    alike), and the init anchor holds the initial centre, whose range came with an assumed length.
    This term holds what the stereo cloud measures instead: where the faces it saw lie. Each point
    is compared with the entry of its viewing ray into the box's footprint
    (:func:`vsrd_mi.geometry.surface.footprint_ray_residuals`, range-scaled to
    ``reference_range``), through :func:`vsrd_mi.geometry.surface.quantile_soft_l1` of ``scale``
    and ``quantile``; a box's term is the mean over its points times its weight, and the loss is
    the sum over boxes divided by their number.

    ``points[n]`` / ``cameras[n]`` are (M, 3) arrays in the optimisation frame (static boxes: the
    points do not move; moving boxes: their points moved to the target time), or None for a box
    without points (weight 0). At most ``max_points`` per box are kept (a fixed random subset,
    drawn for box ``n`` with the seed ``(seed, n)``, so that it does not depend on the other
    boxes). With ``by_range`` each point weighs the quantile of its own horizontal range
    (:func:`vsrd_mi.geometry.surface.range_quantile`, ``quantile`` at ``reference_range``, at
    least ``min_quantile``) instead of ``quantile`` itself.
    """

    DRJIT_STRUCT = {"box": object, "w": object, "points": object, "cameras": object, "quantile": object}

    def __init__(self, points: list, cameras: list, weights: np.ndarray, scale: float,
                 reference_range: float, max_points: int, quantile: float, seed: int = 0,
                 by_range: bool = False, min_quantile: float = 0.0):
        self.count = len(points)
        self.quantile = float(quantile)
        self.scale, self.reference_range = float(scale), float(reference_range)
        box, lane_w, pts, cams = [], [], [], []
        for n, (p, c) in enumerate(zip(points, cameras)):
            if p is None or len(p) == 0 or weights[n] <= 0:
                continue
            if len(p) > max_points:  # each box its own draw: it must not depend on the other boxes
                keep = np.sort(np.random.default_rng([seed, n]).choice(len(p), max_points, replace=False))
            else:
                keep = slice(None)
            p, c = np.asarray(p)[keep], np.asarray(c)[keep]
            box.append(np.full(len(p), n))
            lane_w.append(np.full(len(p), weights[n] / len(p)))
            pts.append(p)
            cams.append(c)
        self.lanes = int(sum(len(b) for b in box))
        self.box = self.w = self.points = self.cameras = None
        if self.lanes:
            pts, cams = np.concatenate(pts), np.concatenate(cams)
            self.box = to_uint(np.concatenate(box))
            self.w = to_float(np.concatenate(lane_w))
            self.points = (to_float(pts[:, 0]), to_float(pts[:, 2]))
            self.cameras = (to_float(cams[:, 0]), to_float(cams[:, 2]))
            if by_range:  # per point, the faces' quantile at its range (horizontal, as the residuals')
                ranges = np.hypot(pts[:, 0] - cams[:, 0], pts[:, 2] - cams[:, 2])
                self.quantile = to_float(range_quantile(ranges, self.quantile, self.reference_range,
                                                        floor=min_quantile))

    @property
    def active(self) -> bool:
        """Whether any box has points and a non-zero weight."""
        return self.lanes > 0

    def residuals(self, dec: DecodedBoxes) -> mi.Float:
        """Each point's range-scaled residual against its box (metres at ``reference_range``)."""
        def g(a):
            return dr.gather(mi.Float, a, self.box)

        cx, cz, cos, sin = g(dec.centre[0]), g(dec.centre[2]), g(dec.cos), g(dec.sin)

        def local(x, z):
            dx, dz = x - cx, z - cz
            return cos * dx - sin * dz, sin * dx + cos * dz

        (px, pz), (qx, qz) = local(*self.points), local(*self.cameras)
        return footprint_ray_residuals(px, pz, qx, qz, g(dec.half[0]), g(dec.half[2]),
                                       self.reference_range, xp=drjit_namespace())

    def loss(self, dec: DecodedBoxes) -> mi.Float:
        """``sum_n w_n mean_k quantile_soft_l1(r_nk) / N`` (metres)."""
        if not self.active:
            return mi.Float(0.0)
        r = self.residuals(dec)
        rho = quantile_soft_l1(r, self.scale, self.quantile, drjit_namespace())
        return dr.sum(self.w * rho) / max(self.count, 1)


def shape_prior_loss(dec: DecodedBoxes, size_init: np.ndarray, yaw_init: np.ndarray,
                     w_size, w_yaw) -> mi.Float:
    """``sum_n (w_size_n |size_n - size_init_n|_1 + w_yaw_n sin^2(yaw_n - yaw_init_n)) / N``.

    ``size`` is the full box size (w, h, l) in metres; ``sin^2`` has period pi, so a box
    initialised backwards costs nothing. The weights are scalars or per-box arrays. An
    optimisation builds the :class:`ShapePrior` once instead.
    """
    return ShapePrior(size_init, yaw_init, w_size, w_yaw).loss(dec)


def eikonal_loss(field: InstanceField, dec: DecodedBoxes, weights, points_local: np.ndarray,
                 step: float) -> mi.Float:
    """``mean (|grad F_k| - 1)^2`` at box-local sample points of every instance (central differences).

    ``points_local`` is (N, P, 3) in units of each box's half-extents (in [-1, 1] and a bit beyond).
    The gradient norm is rotation invariant, so the differences are taken along the box-local
    axes; all instances and all 6 offsets go through one batched residual evaluation.
    """
    n, p_count, _ = points_local.shape
    width = 6 * p_count
    offsets = np.zeros((width, 3))
    for i, (axis, sign) in enumerate((a, s) for a in range(3) for s in (1.0, -1.0)):
        offsets[i * p_count:(i + 1) * p_count, axis] = sign * step
    pts, boxes = [], []
    for k in range(n):
        bv = field.view(dec, k, dr.zeros(mi.Float, width), width)
        tiled = np.tile(points_local[k], (6, 1))
        pl = mi.Vector3f(*[to_float(tiled[:, j]) * bv.half[j] + to_float(offsets[:, j]) for j in range(3)])
        pts.append(pl)
        boxes.append(box_sdf_local(pl, bv.half))
    res = field.residual.evaluate_grouped(weights, list(range(n)), pts)
    lane = dr.arange(mi.UInt32, p_count)
    total = mi.Float(0.0)
    for k in range(n):
        f = boxes[k] + res[k]
        grad = [(dr.gather(mi.Float, f, lane + (2 * a) * p_count)
                 - dr.gather(mi.Float, f, lane + (2 * a + 1) * p_count)) / (2.0 * step) for a in range(3)]
        norm = dr.safe_sqrt(grad[0] * grad[0] + grad[1] * grad[1] + grad[2] * grad[2])
        total = total + mean((norm - 1.0) ** 2)
    return total / max(n, 1)
