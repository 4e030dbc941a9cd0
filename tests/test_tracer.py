"""Tests of the ``sdf_tracer`` integrator against an independent NumPy ray/box slab test."""

from __future__ import annotations

import numpy as np
import pytest

import vsrd_mi  # noqa: F401  (sets the variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties

DEPTH_TOL = 1e-4  # m, required depth accuracy


# ------------------------------------------------------------------------------------------------
# Independent reference (float64 NumPy)
# ------------------------------------------------------------------------------------------------


def rot_y(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def slab_reference(o, d, time, boxes):
    """Nearest entry of each ray into the boxes at the ray's time.

    Returns ``(t, instance, normal, gap, inside)``: ``t = inf`` / ``instance = -1`` for misses;
    the normal is the world normal of the entered face; ``gap`` is the distance along the ray
    between the last two slab entries (small: the hit is near an edge, where the face is
    ill-defined); ``inside``: the origin lies inside a box.
    """
    n = len(o)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    best_t = np.full(n, np.inf)
    inst = np.full(n, -1)
    normal = np.zeros((n, 3))
    gap = np.full(n, np.inf)
    inside = np.zeros(n, dtype=bool)
    for k in range(len(boxes["centre"])):
        centre = boxes["centre"][k] + boxes["dynamic"][k] * boxes["velocity"][k] * time[:, None]
        r = rot_y(boxes["yaw"][k])
        half = boxes["size"][k] / 2.0
        ol = (o - centre) @ r  # R^T (o - c), row vectors
        dl = d @ r
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (-half - ol) / dl
            tb = (half - ol) / dl
        tnear = np.minimum(ta, tb)
        tfar = np.maximum(ta, tb)
        t0 = tnear.max(axis=1)
        t1 = tfar.min(axis=1)
        hit = (t0 <= t1) & (t0 > 0)
        inside |= (t0 <= 0) & (t1 >= 0)
        closer = hit & (t0 < best_t)
        axis = tnear.argmax(axis=1)
        srt = np.sort(tnear, axis=1)
        nl = np.zeros((n, 3))
        nl[np.arange(n), axis] = -np.sign(dl[np.arange(n), axis])
        best_t = np.where(closer, t0, best_t)
        inst = np.where(closer, k, inst)
        normal = np.where(closer[:, None], nl @ r.T, normal)
        gap = np.where(closer, srt[:, 2] - srt[:, 1], gap)
    return best_t, inst, normal, gap, inside


def random_boxes(rng, n, dynamic_fraction=0.5):
    """Random boxes 3-80 m in front of the camera, random yaw, sizes, some moving."""
    dist = rng.uniform(3.0, 80.0, n)
    bearing = rng.uniform(-0.5, 0.5, n)
    centres = np.column_stack([dist * np.sin(bearing), rng.uniform(-1.0, 2.0, n), dist * np.cos(bearing)])
    sizes = np.column_stack([rng.uniform(1.3, 2.5, n), rng.uniform(1.2, 2.8, n), rng.uniform(2.5, 6.5, n)])
    yaws = rng.uniform(-np.pi, np.pi, n)
    velocities = rng.normal(0.0, 1.0, (n, 3)) * np.array([1.0, 0.0, 1.0])
    dynamic = (rng.uniform(size=n) < dynamic_fraction).astype(float)
    return centres, sizes, yaws, velocities, dynamic


def load_tracer(centres, sizes, yaws, velocities=None, dynamic=None, **extra):
    return mi.load_dict({"type": "sdf_tracer",
                         **box_properties(centres, sizes, yaws, velocities, dynamic), **extra})


def rays_at_faces(rng, boxes, n_per_box, time_range, sin_range, offset_range=(0.0, 0.0)):
    """Rays aimed at random points of random faces of every box at a given incidence.

    ``sin_range``: sine of the angle between the ray and the face plane. ``offset_range``: the
    aim point is pushed this far outwards along the face normal (> 0: a near miss of that face).
    """
    o, d, t = [], [], []
    for k in range(len(boxes["centre"])):
        half = boxes["size"][k] / 2.0
        r = rot_y(boxes["yaw"][k])
        for _ in range(n_per_box):
            tau = rng.uniform(*time_range)
            centre = boxes["centre"][k] + boxes["dynamic"][k] * boxes["velocity"][k] * tau
            axis = rng.integers(3)
            sgn = rng.choice([-1.0, 1.0])
            nl = np.zeros(3)
            nl[axis] = sgn
            q = rng.uniform(-0.9, 0.9, 3) * half
            q[axis] = sgn * half[axis] + sgn * rng.uniform(*offset_range)
            tangent = np.zeros(3)
            others = [a for a in range(3) if a != axis]
            phi = rng.uniform(0, 2 * np.pi)
            tangent[others[0]], tangent[others[1]] = np.cos(phi), np.sin(phi)
            s = rng.uniform(*sin_range)
            dl = -s * nl + np.sqrt(1 - s * s) * tangent
            dist = rng.uniform(3.0, 30.0)
            origin_l = q - dist * dl
            o.append(centre + r @ origin_l)
            d.append(r @ dl)
            t.append(tau)
    return np.array(o), np.array(d), np.array(t)


def trace(integ, o, d, time):
    out = integ.trace_rays(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32)),
                           mi.Float(time.astype(np.float32)))
    return {k: np.array(v) for k, v in out.items()}


def check_against_reference(integ, o, d, time):
    """Compare the tracer with the slab reference on float32-rounded rays; return #hits."""
    o = o.astype(np.float32).astype(np.float64)
    d = d.astype(np.float32).astype(np.float64)
    time = time.astype(np.float32).astype(np.float64)
    boxes = integ.boxes()  # the decoded (single-precision) parameters
    boxes = {k: np.asarray(v, dtype=np.float64) for k, v in boxes.items()}
    t_ref, i_ref, n_ref, gap, inside = slab_reference(o, d, time, boxes)
    out = trace(integ, o, d, time)
    # a ray starting inside a box hits it at t = 0
    assert np.all(out["hit"][inside]) and np.all(out["t"][inside] == 0)
    keep = ~inside
    out = {k: v[..., keep] for k, v in out.items()}
    t_ref, i_ref, n_ref, gap = t_ref[keep], i_ref[keep], n_ref[keep], gap[keep]
    hit_ref = i_ref >= 0
    np.testing.assert_array_equal(out["hit"], hit_ref)
    np.testing.assert_array_equal(out["instance"][~hit_ref], -1)
    assert np.all(out["t"][~hit_ref] == 0)
    err = np.abs(out["t"][hit_ref] - t_ref[hit_ref])
    assert err.max() <= DEPTH_TOL, f"max depth error {err.max():.3g} m"
    np.testing.assert_array_equal(out["depth"], out["t"])  # no sensor: depth = t
    np.testing.assert_array_equal(out["instance"][hit_ref], i_ref[hit_ref])
    clear = hit_ref & (gap > 1e-3)  # hit point not on an edge
    normal = out["normal"].T
    dots = np.sum(normal[clear] * n_ref[clear], axis=1)
    assert np.all(dots > 0.999), f"normal mismatch {dots.min()}"
    return int(hit_ref.sum())


# ------------------------------------------------------------------------------------------------
# Tests
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_boxes():
    rng = np.random.default_rng(7)
    centres, sizes, yaws, vel, dyn = random_boxes(rng, 5)
    integ = load_tracer(centres, sizes, yaws, vel, dyn)
    return integ, {k: np.asarray(v, float) for k, v in integ.boxes().items()}


def test_depth_instance_normal_match_slab_reference(scene_boxes):
    integ, boxes = scene_boxes
    rng = np.random.default_rng(1)
    o, d, t = rays_at_faces(rng, boxes, 40, (-3.0, 3.0), (0.2, 1.0))
    assert check_against_reference(integ, o, d, t) >= 150
    assert integ.last_stats["unconverged"] == 0


def test_near_grazing_rays(scene_boxes):
    integ, boxes = scene_boxes
    rng = np.random.default_rng(2)
    o, d, t = rays_at_faces(rng, boxes, 40, (-3.0, 3.0), (0.03, 0.1))
    assert check_against_reference(integ, o, d, t) >= 150
    assert integ.last_stats["unconverged"] == 0


def test_near_misses_and_random_rays(scene_boxes):
    integ, boxes = scene_boxes
    rng = np.random.default_rng(3)
    # rays parallel to a face, just outside it: mostly misses (unless another box is in the way)
    o1, d1, t1 = rays_at_faces(rng, boxes, 20, (-3.0, 3.0), (0.0, 0.0), (1e-3, 0.05))
    n = 200
    o2 = rng.uniform(-1.0, 1.0, (n, 3))
    d2 = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.3, 0.3, n), np.ones(n)])
    t2 = rng.uniform(-3.0, 3.0, n)
    o, d, t = np.vstack([o1, o2]), np.vstack([d1, d2]), np.concatenate([t1, t2])
    hits = check_against_reference(integ, o, d, t)
    assert 0 < hits < len(o)


def test_static_box_ignores_time():
    integ = load_tracer([[0.0, 0.0, 10.0]], [[2.0, 1.5, 4.0]], [0.0], [[5.0, 0.0, 0.0]], [0.0])
    o = np.zeros((2, 3))
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    out = trace(integ, o, d, np.array([0.0, 7.0]))
    np.testing.assert_allclose(out["t"], [8.0, 8.0], atol=DEPTH_TOL)
    np.testing.assert_allclose(out["normal"].T, [[0, 0, -1]] * 2, atol=1e-6)


def test_render_with_sensor_aovs_and_traverse():
    # one box straight ahead, yaw 0: its front face is the plane z = 10 - 2 = 8 (camera z)
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60.0,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, 1], [0, -1, 0]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 16, "rfilter": {"type": "box"}}},
        "integrator": {"type": "sdf_tracer", "id": "tracer",
                       **box_properties([[0.0, 0.0, 10.0]], [[2.0, 1.5, 4.0]], [0.0])},
    })
    params = mi.traverse(scene)
    for key in ("tracer.centre", "tracer.size", "tracer.yaw", "tracer.velocity", "tracer.dynamic"):
        assert key in params
    assert not any("rdf_" in key for key in params.keys())
    img = np.array(mi.render(scene, spp=1))
    assert img.shape == (16, 24, 8)
    inst, depth, nrm = img[..., 3], img[..., 4], img[..., 5:8]
    hit = inst == 0
    assert set(np.unique(inst)) == {-1.0, 0.0}
    assert 0 < hit.sum() < hit.size
    np.testing.assert_allclose(depth[hit], 8.0, atol=DEPTH_TOL)  # z-depth, not distance
    assert np.all(depth[~hit] == 0) and np.all(img[~hit][:, :3] == 0)
    np.testing.assert_allclose(nrm[hit], [[0, 0, -1]] * int(hit.sum()), atol=1e-6)
    assert np.all(img[hit][:, :3].max(axis=1) > 0)
    # moving the box through mi.traverse (in metres) changes the render
    centre = np.array(params["tracer.centre"])
    params["tracer.centre"] = mi.Float(centre + np.array([0.0, 0.0, 0.3], dtype=np.float32))
    params.update()
    z_new = float(scene.integrator().boxes()["centre"][0, 2]) - 2.0
    assert z_new == pytest.approx(8.3, abs=1e-5)
    img2 = np.array(mi.render(scene, spp=1))
    hit2 = img2[..., 3] == 0
    assert z_new > 8.1
    np.testing.assert_allclose(img2[..., 4][hit2], z_new, atol=DEPTH_TOL)


def test_residual_on_no_nan_and_not_nearer_than_box():
    rng = np.random.default_rng(5)
    centres, sizes, yaws, vel, dyn = random_boxes(rng, 3)
    box = load_tracer(centres, sizes, yaws, vel, dyn)
    res = load_tracer(centres, sizes, yaws, vel, dyn, residual=True)
    boxes = {k: np.asarray(v, float) for k, v in box.boxes().items()}
    o, d, t = rays_at_faces(rng, boxes, 30, (-2.0, 2.0), (0.3, 1.0))
    a, b = trace(box, o, d, t), trace(res, o, d, t)
    for v in b.values():
        assert np.all(np.isfinite(v.astype(float)))
    assert np.all(~b["hit"] | a["hit"])  # the residual surface lies inside the boxes
    both = a["hit"] & b["hit"]
    assert both.sum() > 0
    assert np.all(b["t"][both] >= a["t"][both] - 1e-5)
    assert np.any(b["t"][both] > a["t"][both] + 1e-3)  # the residual does move the surface
    n = b["normal"].T[b["hit"]]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    # the hit is a root of the scene SDF as computed by the sdf module itself
    from vsrd_plugins.sdf import scene_sdf
    field = res.field
    with dr.suspend_grad():
        dec, w = field.decode(), field.residual_weights()
        dn = d / np.linalg.norm(d, axis=1, keepdims=True)
        sel = b["hit"]
        vals = []
        for delta in (-2e-3, 2e-3):
            p = o[sel] + (b["t"][sel] + delta)[:, None] * dn[sel]
            f = scene_sdf(field.instance_sdfs(dec, mi.Point3f(p.T.astype(np.float32)),
                                              mi.Float(t[sel].astype(np.float32)), w, reach=1.0))
            vals.append(np.array(f))
    assert np.all(vals[0] > 0) and np.all(vals[1] < 0)


def test_bad_properties():
    # mi.load_dict re-raises the plugin's ValueError as a RuntimeError carrying its message
    with pytest.raises((ValueError, RuntimeError), match="max_iterations"):
        load_tracer([[0, 0, 10]], [[2, 1.5, 4]], [0.0], max_iterations=0)
    with pytest.raises((ValueError, RuntimeError), match="near < far"):
        load_tracer([[0, 0, 10]], [[2, 1.5, 4]], [0.0], near=5.0, far=1.0)
