r"""Boxes: their decoded parameters and signed distance, exact along rays (kinks, ridges, bends).

The scene frame is y-down (x right, y down, z forward); a box's yaw rotates about +y,
``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``, so its length axis (local +z) points along
``(sin yaw, 0, cos yaw)``. In box-local coordinates ``q = |p| - h`` (``h`` the half extents)
the box SDF is

.. math::

    B(p) = \sqrt{\lVert \max(q, 0) \rVert^2} + \min(\max(q_x, q_y, q_z), 0)

with a safe square root whose derivative at 0 is 0, so points inside the box, on faces and on
edges have finite gradients. Along a ray ``B`` is convex; inside the box it is the upper envelope
of six face planes (piecewise linear, kinks where the nearest face changes), outside smooth but
bending where the ray crosses the plane of a face beside it. The functions below find those
places and give the envelope (Danskin) gradient where a minimum sits on a ridge
(``docs/integrators.md``, "Gradients at ridges and kinks").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import drjit as dr
import mitsuba as mi


@dataclass
class DecodedBoxes:
    """Decoded per-instance box parameters as small (width-N) Dr.Jit arrays."""

    half: list  # 3 x Float(N)
    centre: list  # 3 x Float(N)
    cos: mi.Float
    sin: mi.Float
    velocity: list  # 3 x Float(N)
    dynamic: mi.Float


@dataclass
class BoxView:
    """One instance's box broadcast to a lane width (full-width gathers: a width-1 broadcast would
    reduce its adjoint in a kernel of its own per use, ``docs/integrators.md``, "Kernel shapes")."""

    half: mi.Vector3f
    centre: mi.Point3f  # already moved to the lane's ray time
    cos: mi.Float
    sin: mi.Float

    def to_local(self, p: mi.Point3f) -> mi.Vector3f:
        """Box-local coordinates of scene-frame points (``R_y^T (p - centre)``)."""
        d = p - self.centre
        return mi.Vector3f(self.cos * d.x - self.sin * d.z, d.y, self.sin * d.x + self.cos * d.z)

    def dir_to_local(self, v: mi.Vector3f) -> mi.Vector3f:
        return mi.Vector3f(self.cos * v.x - self.sin * v.z, v.y, self.sin * v.x + self.cos * v.z)

    def dir_to_world(self, v: mi.Vector3f) -> mi.Vector3f:
        return mi.Vector3f(self.cos * v.x + self.sin * v.z, v.y, -self.sin * v.x + self.cos * v.z)


def box_sdf_local(p: mi.Vector3f, half: mi.Vector3f) -> mi.Float:
    """Signed distance to an axis-aligned box of half-extents ``half`` centred at the origin."""
    q = dr.abs(p) - half
    qo = dr.maximum(q, 0.0)
    outside = dr.safe_sqrt(dr.squared_norm(qo))
    inside = dr.minimum(dr.maximum(dr.maximum(q.x, q.y), q.z), 0.0)
    return outside + inside


def box_sdf_local_grad(p: mi.Vector3f, half: mi.Vector3f) -> tuple[mi.Float, mi.Vector3f, mi.Vector3f]:
    """:func:`box_sdf_local` with its derivatives ``(B, dB/dp, dB/dhalf)`` in closed form (no AD).

    ``dB/dq_i = max(q_i, 0) / |max(q, 0)|`` outside (0 where the squared norm is at most
    ``dr.epsilon``, as Dr.Jit's safe square root has it), plus 1 for the largest ``q_i`` where
    ``max_i q_i <= 0``; ``dq_i/dp_i = sign(p_i)`` and ``dq_i/dhalf_i = -1``. At ties it follows
    Dr.Jit's AD of :func:`box_sdf_local` exactly (``abs'(0) = 0``; ``maximum(a, b)`` sends the
    gradient to ``a`` only where ``a > b``, ``minimum(a, b)`` to ``a`` where ``a <= b``), so the
    adaptive sampler's lanes and the AD paths (dense, ``integrate_at``) differentiate the same
    function the same way, on box faces and edges too."""
    q = dr.abs(p) - half
    qo = dr.maximum(q, 0.0)
    sq = dr.squared_norm(qo)
    outside = dr.safe_sqrt(sq)
    m_xy = dr.maximum(q.x, q.y)
    m = dr.maximum(m_xy, q.z)
    inv = dr.select(sq > dr.epsilon(mi.Float), dr.rcp(outside), 0.0)
    on_inside = m <= 0.0  # minimum(m, 0) passes the gradient to m
    xy = on_inside & (m_xy > q.z)
    gq = mi.Vector3f(dr.fma(qo.x, inv, dr.select(xy & (q.x > q.y), 1.0, 0.0)),
                     dr.fma(qo.y, inv, dr.select(xy & ~(q.x > q.y), 1.0, 0.0)),
                     dr.fma(qo.z, inv, dr.select(on_inside & ~(m_xy > q.z), 1.0, 0.0)))
    sgn = dr.select(p > 0.0, 1.0, dr.select(p < 0.0, -1.0, 0.0))
    return outside + dr.minimum(m, 0.0), gq * sgn, -gq


#: Faces within this much (m) of the largest face distance count as meeting at a ridge in
#: :func:`box_sdf_ray_local`: above the float32 error of box-local coordinates 100 m away and the
#: adaptive sampler's golden-section bracket (which puts a sample on the ridge), far below 1/s.
RIDGE_TOLERANCE = 1e-3


def envelope_weight(ga: mi.Float, gb: mi.Float) -> mi.Float:
    """Danskin weight ``lambda_a = g_b / (g_b - g_a)`` of function ``a`` where two functions of
    opposite slopes ``g_a``, ``g_b`` along a ray cross at the ray's extremum of their max (or
    min): the blend ``lambda_a a + (1 - lambda_a) b`` has slope zero there. Needs
    ``g_a != g_b``."""
    return gb / (gb - ga)


def envelope_blend(value: mi.Float, fa: mi.Float, fb: mi.Float, lam: mi.Float) -> mi.Float:
    """``value`` with the gradient ``lam dfa + (1 - lam) dfb`` (the envelope gradient of the
    extremum where ``fa`` and ``fb`` cross; see :func:`envelope_weight`)."""
    return dr.detach(value) + lam * (fa - dr.detach(fa)) + (1.0 - lam) * (fb - dr.detach(fb))


def box_sdf_ray_local(p: mi.Vector3f, d: mi.Vector3f, half: mi.Vector3f,
                      tol: float | mi.Float = RIDGE_TOLERANCE, kink_lam: mi.Float | None = None) -> mi.Float:
    r""":func:`box_sdf_local` at a point of a ray with direction ``d``, with the envelope gradient
    at the ray's deepest point inside the box.

    Inside, ``B = max_j v_j`` over the six face planes ``v = (p_i - h_i, -p_i - h_i)``. Along the
    ray ``B`` is convex and piecewise linear; its minimum lies on a ridge where a decreasing face
    ``a`` (slope ``g_a < 0``, ``g = (d_i, -d_i)``) meets an increasing face ``b`` (``g_b > 0``):
    two adjacent faces, or a face pair's mid-plane. By Danskin's theorem the minimum's derivative
    w.r.t. any box parameter is

    .. math:: \lambda_a \partial v_a + \lambda_b \partial v_b, \qquad
              \lambda_a = \frac{g_b}{g_b - g_a}, \; \lambda_b = 1 - \lambda_a

    (the blend whose slope along the ray is zero), while AD of the max follows one face, chosen by
    which side of the ridge the sample lies on. NeuS opacity telescopes to ``Phi_s`` of a ray's
    deepest sample, so a one-sided gradient there is the whole gradient of that ray's label. Where
    the faces within ``tol`` of the max include a decreasing and an increasing one (the most
    negative and most positive slopes are blended), this returns ``B`` with the blended gradient;
    elsewhere exactly :func:`box_sdf_local`. ``d`` need not be normalised (``lambda`` is scale-free).
    ``kink_lam``: per point a kink's own weight, see :func:`ridge_faces`.
    """
    f = box_sdf_local(p, half)
    faces = face_planes(p, half)
    ridge, ia, ib, lam = ridge_faces(p, d, half, tol, kink_lam)

    def face(idx):
        out = faces[5]
        for j in range(4, -1, -1):
            out = dr.select(idx == j, faces[j], out)
        return out

    return dr.select(ridge, envelope_blend(f, face(ia), face(ib), lam), f)


def face_planes(p: mi.Vector3f, half: mi.Vector3f) -> list[mi.Float]:
    """The six face planes of a box at box-local ``p``: ``p_j - h_j`` (face ``j < 3``) and
    ``-p_j - h_j`` (face ``j + 3``); inside the box, :func:`box_sdf_local` is their max."""
    return [p[i] - half[i] for i in range(3)] + [-p[i] - half[i] for i in range(3)]


#: At most this many kinks of the box SDF along a ray inside its box (:func:`box_ray_kinks`):
#: the upper envelope of six lines whose slopes increase at every kink has at most six pieces.
BOX_RAY_KINKS = 5


def box_ray_kinks(o: mi.Vector3f, d: mi.Vector3f, half: mi.Vector3f, t0: mi.Float, t1: mi.Float,
                  count: int = BOX_RAY_KINKS) -> list[mi.Float]:
    """The kinks of :func:`box_sdf_local` along the box-local ray ``o + t d`` within ``(t0, t1)``,
    a stretch inside the box (detached): ``count`` arrays, ascending, ``-1`` past the last kink.

    Inside the box ``B`` is the max of the six :func:`face_planes`, each linear along the ray:
    ``B`` is their upper envelope, convex and piecewise linear, and its slope increases at every
    kink. Walking from ``t0``, where the largest plane (of ties, the steepest) is the envelope,
    the next kink is the earliest crossing of the current plane with a steeper one (of ties, the
    steepest takes over). Parallel planes never cross; ``d`` need not be normalised."""
    with dr.suspend_grad():
        o, d, half, t0, t1 = (dr.detach(x) for x in (o, d, half, t0, t1))
        v0 = face_planes(o + t0 * d, half)  # each plane: v0_j + g_j (t - t0)
        slopes = [d[i] for i in range(3)] + [-d[i] for i in range(3)]
        vc, gc = v0[0], slopes[0]
        for v, g in zip(v0[1:], slopes[1:]):
            take = (v > vc) | ((v == vc) & (g > gc))
            vc, gc = dr.select(take, v, vc), dr.select(take, g, gc)
        out, at = [], mi.Float(0.0)  # at: the last kink's offset from t0
        for _ in range(count):
            best, vb, gb = mi.Float(dr.inf), vc, gc
            for v, g in zip(v0, slopes):
                steeper = g > gc
                cross = dr.maximum((vc - v) / dr.select(steeper, g - gc, 1.0), at)
                take = steeper & ((cross < best) | ((cross == best) & (g > gb)))
                best, vb, gb = dr.select(take, cross, best), dr.select(take, v, vb), dr.select(take, g, gb)
            t = t0 + best
            out.append(dr.select(t < t1, t, -1.0))
            at, vc, gc = dr.select(dr.isfinite(best), best, at), vb, gb
        return out


def box_ray_bends(o: mi.Vector3f, d: mi.Vector3f, half: mi.Vector3f, t0: mi.Float,
                  t1: mi.Float) -> tuple[list[mi.Float], list[mi.Float]]:
    """Where the box-local ray ``o + t d`` crosses the plane of a face outside the box within
    ``(t0, t1)``, and :func:`box_sdf_local` there (detached): six ``(t, B)``, ``t = -1`` for
    none.

    Outside the box ``B`` is the distance to its nearest point, smooth (C1) but bending where
    that point moves from a face onto an edge, or from an edge onto a corner: where the ray
    crosses the plane of a face beside it. Along the ray the bend is about as wide as ``B``
    there, and its slope turns by up to the ray's direction cosine with that face's normal: a
    ray passing close to an edge sees a near-kink."""
    with dr.suspend_grad():
        o, d, half, t0, t1 = (dr.detach(x) for x in (o, d, half, t0, t1))
        ts, bs = [], []
        for i in range(3):
            moving = d[i] != 0.0
            inv = dr.select(moving, dr.rcp(dr.select(moving, d[i], 1.0)), 0.0)
            for side in (1.0, -1.0):
                t = (side * half[i] - o[i]) * inv
                b = box_sdf_local(o + t * d, half)
                ts.append(dr.select(moving & (t > t0) & (t < t1) & (b > 0.0), t, -1.0))
                bs.append(b)
        return ts, bs


def ridge_faces(p: mi.Vector3f, d: mi.Vector3f, half: mi.Vector3f, tol: float | mi.Float = RIDGE_TOLERANCE,
                kink_lam: mi.Float | None = None) -> tuple[mi.Bool, mi.UInt32, mi.UInt32, mi.Float]:
    """The ridge of :func:`box_sdf_ray_local` at ``p`` (detached): whether the faces within
    ``tol`` of the max include a decreasing and an increasing one along ``d``, the two blended
    faces ``a`` (steepest decreasing) and ``b`` (steepest increasing) as indices into
    :func:`face_planes`, and ``lambda_a``.

    Where ``kink_lam >= 0`` the point is a kink of ``B`` along the ray at which a field
    ``F = B + R`` has a local minimum, with that weight from ``F``'s own slopes on either side
    (``R`` moves the minimum's envelope off ``B``'s, and makes kinks minima whose faces both
    rise or both fall): there the blended faces are the near faces of the least (``a``, the
    envelope before the kink) and the greatest slope (``b``, after it)."""
    with dr.suspend_grad():
        p, d, half = dr.detach(p), dr.detach(d), dr.detach(half)
        v = face_planes(p, half)
        m = dr.maximum(dr.maximum(dr.maximum(v[0], v[1]), dr.maximum(v[2], v[3])), dr.maximum(v[4], v[5]))
        slopes = [d[i] for i in range(3)] + [-d[i] for i in range(3)]
        # the near faces of the least and the greatest slope: at a ridge the steepest decreasing
        # and increasing one, at a kink the envelope before and after it
        ia, ib = mi.UInt32(6), mi.UInt32(6)
        ga, gb = mi.Float(dr.inf), mi.Float(-dr.inf)
        for j in range(6):
            near = (m - v[j]) <= tol
            lo_j, hi_j = near & (slopes[j] < ga), near & (slopes[j] > gb)
            ia, ga = dr.select(lo_j, j, ia), dr.select(lo_j, slopes[j], ga)
            ib, gb = dr.select(hi_j, j, ib), dr.select(hi_j, slopes[j], gb)
        ridge = (m < 0.0) & (ga < 0.0) & (gb > 0.0)
        lam = envelope_weight(dr.select(ridge, ga, -1.0), dr.select(ridge, gb, 1.0))
        if kink_lam is not None:
            kink = kink_lam >= 0.0
            ridge = dr.select(kink, (m < 0.0) & (ga < gb), ridge)
            lam = dr.select(kink, kink_lam, lam)
    return ridge, ia, ib, lam


def ridge_local_grad(ia: mi.UInt32, ib: mi.UInt32, lam: mi.Float) -> tuple[mi.Vector3f, mi.Vector3f]:
    """``(dB/dp, dB/dhalf)`` of the envelope at a ridge (:func:`ridge_faces`): ``lambda`` times
    face ``a``'s plane gradient plus ``1 - lambda`` times face ``b``'s (:func:`face_planes`), as
    :func:`box_sdf_ray_local`'s AD gives it."""
    gp, gh = [mi.Float(0.0)] * 3, [mi.Float(0.0)] * 3
    for face, w in ((ia, lam), (ib, 1.0 - lam)):
        for i in range(3):
            on = (face == i) | (face == i + 3)
            gp[i] = gp[i] + dr.select(on, dr.select(face == i, w, -w), 0.0)
            gh[i] = gh[i] - dr.select(on, w, 0.0)
    return mi.Vector3f(*gp), mi.Vector3f(*gh)


def box_normal_local(p: mi.Vector3f, half: mi.Vector3f) -> mi.Vector3f:
    """Outward unit gradient of :func:`box_sdf_local` (inside: normal of the nearest face)."""
    q = dr.abs(p) - half
    sgn = dr.select(p >= 0, 1.0, -1.0)
    qo = dr.maximum(q, 0.0)
    n_out = qo * sgn
    inside = dr.max(q) <= 0
    qx_max = (q.x >= q.y) & (q.x >= q.z)
    qy_max = ~qx_max & (q.y >= q.z)
    n_in = mi.Vector3f(dr.select(qx_max, sgn.x, 0.0), dr.select(qy_max, sgn.y, 0.0),
                       dr.select(~qx_max & ~qy_max, sgn.z, 0.0))
    n = dr.select(inside, n_in, n_out)
    return n / dr.maximum(dr.norm(n), 1e-12)


def ray_box_interval(o_l: mi.Vector3f, d_l: mi.Vector3f, half) -> tuple[mi.Float, mi.Float]:
    """Slab test in box-local coordinates: entry and exit ray parameters ``(t0, t1)``.

    Empty when ``t0 > t1``. Safe for direction components equal to 0 (rays parallel to a face).
    """
    tiny = 1e-12
    inv = mi.Vector3f(*[1.0 / dr.select(dr.abs(c) < tiny, dr.select(c >= 0, tiny, -tiny), c)
                        for c in (d_l.x, d_l.y, d_l.z)])
    ta = (-half - o_l) * inv
    tb = (half - o_l) * inv
    t0 = dr.max(dr.minimum(ta, tb))
    t1 = dr.min(dr.maximum(ta, tb))
    return t0, t1


# ----------------------------------------------------------------------------------------------
# Residual field
# ----------------------------------------------------------------------------------------------


def scene_sdf(sdfs: Sequence[mi.Float]) -> mi.Float:
    """Scene SDF: minimum over instances (gradient to the first instance on exact ties)."""
    f = sdfs[0]
    for g in sdfs[1:]:
        f = dr.minimum(f, g)
    return f


def softmin_labels(sdfs: Sequence[mi.Float], tau) -> list[mi.Float]:
    """Soft instance labels ``softmin(F_k / tau)`` (stable: shifted by the detached minimum)."""
    m = dr.detach(scene_sdf(sdfs))
    e = [dr.exp((m - f) / tau) for f in sdfs]
    z = e[0]
    for x in e[1:]:
        z = z + x
    inv = 1.0 / z
    return [x * inv for x in e]
