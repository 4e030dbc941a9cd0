"""Instance SDF model (vsrd_plugins.sdf) against independent NumPy references."""

from __future__ import annotations

import numpy as np
import pytest

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties
from vsrd_plugins.sdf import (InstanceField, ResidualConfig, box_ray_kinks, box_sdf_local, box_sdf_local_grad,
                              box_sdf_ray_local, ray_box_interval, sigmoid, softplus)


def np_box_sdf(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Exact box SDF by brute force: distance to the closest surface point, signed.

    Outside: distance to the clamped point. Inside: minus the distance to the nearest face.
    Written independently of the closed form ``|max(q,0)| + min(max q, 0)``.
    """
    clamped = np.clip(p, -half, half)
    outside = np.linalg.norm(p - clamped, axis=1)
    inside = np.all(np.abs(p) < half, axis=1)
    face_dist = np.min(half - np.abs(p), axis=1)
    return np.where(inside, -face_dist, outside)


def props_of(d: dict) -> mi.Properties:
    p = mi.Properties()
    for k, v in d.items():
        p[k] = v
    return p


def make_field(centre, size, yaw, velocity=None, dynamic=None, **extra) -> InstanceField:
    """An instance field of the given boxes (``extra``: further properties, e.g. ``residual``)."""
    return InstanceField(props_of({**box_properties(centre, size, yaw, velocity, dynamic), **extra}), "test")


def vec(a: np.ndarray) -> mi.Vector3f:
    return mi.Vector3f(np.ascontiguousarray(a.T, dtype=np.float32))


def test_box_sdf_matches_numpy_reference():
    rng = np.random.default_rng(1)
    half = np.array([0.9, 0.75, 2.2])
    pts = [rng.uniform(-4, 4, (400, 3)),                       # anywhere
           rng.uniform(-1, 1, (200, 3)) * half]                # inside
    # on faces, edges and corners: snap 1, 2 or 3 coordinates to +-half
    for n_snap in (1, 2, 3):
        q = rng.uniform(-1, 1, (100, 3)) * half
        for i in range(100):
            axes = rng.choice(3, n_snap, replace=False)
            q[i, axes] = rng.choice([-1, 1], n_snap) * half[axes]
        pts.append(q)
    p = np.concatenate(pts)
    got = np.array(box_sdf_local(vec(p), mi.Vector3f(*[float(h) for h in half])))
    ref = np_box_sdf(p.astype(np.float32).astype(np.float64), half)
    np.testing.assert_allclose(got, ref, atol=2e-6)


@pytest.mark.parametrize("where", ["inside", "face", "edge", "corner", "centre", "outside"])
def test_box_sdf_gradients_finite(where):
    half = np.array([1.0, 0.8, 2.0])
    p = {"inside": [0.3, -0.2, 0.5], "face": [1.0, 0.1, 0.3], "edge": [1.0, 0.8, 0.3],
         "corner": [1.0, -0.8, 2.0], "centre": [0.0, 0.0, 0.0], "outside": [2.0, 1.5, -3.0]}[where]
    pv = mi.Vector3f(*[dr.opaque(mi.Float, v) for v in p])
    hv = mi.Vector3f(*[dr.opaque(mi.Float, v) for v in half])
    dr.enable_grad(pv, hv)
    f = box_sdf_local(pv, hv)
    dr.backward(f)
    grads = np.array([dr.grad(c)[0] for c in (*pv, *hv)])
    assert np.all(np.isfinite(grads)), grads
    # the gradient w.r.t. the point has norm 1 off the surface's singular set (and <= 1 on it)
    gn = np.linalg.norm(grads[:3])
    assert gn <= 1.0 + 1e-6
    if where in ("inside", "outside", "face"):
        assert gn == pytest.approx(1.0, abs=1e-6)


def np_ray_min(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[float, float]:
    """``(t*, min_t B(o + t d))`` of the inside box SDF along a ray, by float64 ternary search
    (``B`` is convex along a line); independent of the plugin's formulas."""
    def b(t):
        return float(np.max(np.abs(o + t * d) - half))
    lo, hi = -20.0, 20.0
    for _ in range(200):
        m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        lo, hi = (lo, m2) if b(m1) < b(m2) else (m1, hi)
    t = 0.5 * (lo + hi)
    return t, b(t)


def test_box_sdf_ray_gradient_is_the_envelope_gradient():
    """At a ray's deepest point inside a box, the gradient w.r.t. the half extents and the box
    position is that of ``min_t B`` (central differences of the brute-force minimum), which a
    one-sided max gradient is not; values equal :func:`box_sdf_local` everywhere."""
    rng = np.random.default_rng(7)
    half = np.array([0.9, 0.75, 2.2])
    eps = 1e-4
    worst_env, worst_plain = 0.0, 0.0
    for _ in range(40):
        o = rng.uniform(-0.6, 0.6, 3) * half
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        t, _ = np_ray_min(o, d, half)
        p = o + t * d
        # central differences of min_t B w.r.t. half (3) and a box shift c (p -> p - c, 3)
        fd = []
        for j in range(6):
            step = np.zeros(6)
            step[j] = eps
            vals = [np_ray_min(o - sg * step[3:], d, half + sg * step[:3])[1] for sg in (1, -1)]
            fd.append((vals[0] - vals[1]) / (2 * eps))
        fd = np.array(fd)
        grads = {}
        for name, fn in (("env", lambda pv, hv: box_sdf_ray_local(pv, mi.Vector3f(*d.tolist()), hv)),
                         ("plain", box_sdf_local)):
            pv = mi.Vector3f(*[dr.opaque(mi.Float, v) for v in p])
            hv = mi.Vector3f(*[dr.opaque(mi.Float, v) for v in half])
            dr.enable_grad(pv, hv)
            f = fn(pv, hv)
            dr.backward(f)
            # a box shift c moves p by -c: dB/dc = -dB/dp
            grads[name] = np.array([dr.grad(c)[0] for c in hv] + [-dr.grad(c)[0] for c in pv])
            assert float(f[0]) == pytest.approx(float(np.max(np.abs(p) - half)), abs=1e-5)
        worst_env = max(worst_env, np.abs(grads["env"] - fd).max())
        worst_plain = max(worst_plain, np.abs(grads["plain"] - fd).max())
    assert worst_env < 1e-2, worst_env
    assert worst_plain > 0.2  # the check can fail: the one-sided gradient is far off somewhere


def test_box_ray_kinks_are_the_slope_changes():
    """``box_ray_kinks`` lists, ascending, every point inside the box where the box SDF's slope
    along the ray changes, checked on a dense NumPy sampling of the SDF (random rays through
    random boxes, a third of them parallel to a face, where ``B`` is flat along it)."""
    rng = np.random.default_rng(21)
    n = 300
    d = rng.normal(size=(n, 3))
    d[: n // 3, 1] = 0.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = rng.normal(0.0, 0.8, (n, 3)) - 8.0 * d
    half = rng.uniform(0.3, 2.5, (n, 3))
    ov, dv, hv = vec(o), vec(d), vec(half)
    t0, t1 = ray_box_interval(ov, dv, hv)
    kinks = np.stack([np.array(k) for k in box_ray_kinks(ov, dv, hv, t0, t1)], axis=1)
    t0, t1 = np.array(t0), np.array(t1)
    checked = 0
    for i in np.where(t1 - t0 > 0.05)[0]:
        ts = np.linspace(t0[i], t1[i], 40001)
        b = np_box_sdf(o[i] + ts[:, None] * d[i], half[i])
        slope = np.diff(b) / np.diff(ts)
        h = ts[1] - ts[0]
        # slope changes: adjacent differences that differ by more than float32 noise, merged
        jump = ts[1:-1][np.abs(np.diff(slope)) > 1e-2]
        found = [x for j, x in enumerate(jump) if j == 0 or x - jump[j - 1] > 3 * h]
        # a kink closer than the sampling to the chord's ends shows as no slope change
        found = [x for x in found if min(x - t0[i], t1[i] - x) > 3 * h]
        k = kinks[i][kinks[i] >= 0.0]
        k = k[np.minimum(k - t0[i], t1[i] - k) > 3 * h]
        assert np.all(np.diff(kinks[i][kinks[i] >= 0.0]) >= 0.0), kinks[i]
        assert len(k) == len(found), (i, k, found)
        np.testing.assert_allclose(k, found, atol=3 * h + 1e-4)
        checked += 1
    assert checked > 100


def test_box_sdf_ray_equals_plain_off_ridges():
    """Away from a ray's deepest point (and outside) values and gradients are box_sdf_local's."""
    rng = np.random.default_rng(8)
    half = mi.Vector3f(0.9, 0.75, 2.2)
    p = rng.uniform(-3, 3, (500, 3))
    d = rng.normal(size=(500, 3))
    pv, dv = vec(p), vec(d)
    dr.enable_grad(pv)
    f_ray = box_sdf_ray_local(pv, dv, half)
    dr.backward(f_ray)
    g_ray = np.array(dr.grad(pv))
    pv2 = vec(p)
    dr.enable_grad(pv2)
    f_plain = box_sdf_local(pv2, half)
    dr.backward(f_plain)
    np.testing.assert_array_equal(np.array(f_ray), np.array(f_plain))
    np.testing.assert_array_equal(g_ray, np.array(dr.grad(pv2)))


def test_box_sdf_closed_form_gradient_is_ad_tie_for_tie():
    """box_sdf_local_grad equals AD of box_sdf_local exactly, on faces, edges, corners, zero
    coordinates and points a hair outside (squared norm below Dr.Jit's safe-sqrt threshold)."""
    rng = np.random.default_rng(12)
    n = 60000
    half = rng.uniform(0.5, 2.0, (n, 3))
    p = rng.uniform(-3, 3, (n, 3))
    kind = rng.integers(0, 6, n)
    p[kind == 1] = half[kind == 1] * np.sign(p[kind == 1])                 # corners
    p[kind == 2, 0] = 0.0                                                   # on a symmetry plane
    p[kind == 3, 0] = half[kind == 3, 0]                                    # on a face
    p[kind == 4] *= 1e-3                                                    # near the centre
    p[kind == 5] = half[kind == 5] * np.sign(p[kind == 5]) * (1 + rng.normal(0, 1e-4, ((kind == 5).sum(), 3)))
    pv, hv = vec(p), vec(half)
    dr.enable_grad(pv, hv)
    f = box_sdf_local(pv, hv)
    dr.backward(f)
    f2, gp, gh = box_sdf_local_grad(dr.detach(pv), dr.detach(hv))
    np.testing.assert_array_equal(np.array(f2), np.array(f))
    np.testing.assert_array_equal(np.array(gp), np.array(dr.grad(pv)))
    np.testing.assert_array_equal(np.array(gh), np.array(dr.grad(hv)))


def lane_setup(rng, n_inst: int, n_lanes: int, residual: bool):
    centres, sizes, yaws = random_boxes(rng, n_inst)
    vel = rng.normal(size=(n_inst, 3))
    dyn = (np.arange(n_inst) % 2).astype(float)
    field = make_field(centres, sizes, yaws, vel, dyn, residual=residual)
    # runs of lanes per instance (as the sampler lays them out) with random run lengths
    runs = rng.integers(1, 20, n_lanes)
    inst = np.repeat(rng.integers(0, n_inst, n_lanes), runs)[:n_lanes]
    local = rng.uniform(-1.3, 1.3, (n_lanes, 3)) * sizes[inst] / 2
    t = rng.uniform(-1, 1, n_lanes)
    c, s_ = np.cos(yaws[inst]), np.sin(yaws[inst])
    world = np.stack([c * local[:, 0] + s_ * local[:, 2], local[:, 1], -s_ * local[:, 0] + c * local[:, 2]], 1)
    p = centres[inst] + world + dyn[inst, None] * vel[inst] * t[:, None]
    return field, vec(p), mi.Float(t.astype(np.float32)), mi.UInt32(inst.astype(np.uint32))


@pytest.mark.parametrize("residual, kinks", [(False, False), (True, False), (False, True)])
def test_lane_sdfs_closed_form_gradient_matches_ad(residual, kinks):
    """lane_sdfs with grad_reach (closed-form box gradient on the lanes near their box, summed
    in runs, the envelope gradient at ridge lanes) gives the same values and reverse- and
    forward-mode gradients as AD of the plain per-lane SDF with the far lanes detached plus the
    AD ridge correction; with ``kinks``, half the ridge lanes carry a kink's own weight
    (``ridge[3]``, :func:`ridge_faces`), which both paths must blend alike."""
    rng = np.random.default_rng(13)
    field, p, t, inst = lane_setup(rng, 5, 3001, residual)
    reach, grad_reach = 0.5, 0.3
    w_np = rng.normal(size=3001).astype(np.float32)
    keys = ("centre", "size", "yaw", "velocity", "dynamic")

    def run(fn, mode):
        for k in keys:
            field.params[k] = dr.detach(field.params[k])
            dr.enable_grad(field.params[k])
        weights = field.residual_weights() if residual else None
        dec = field.decode()
        f = fn(dec, weights)
        if mode == "reverse":
            dr.backward(dr.sum(f * mi.Float(w_np)))
            return np.array(dr.detach(f)), np.concatenate([np.array(dr.grad(field.params[k])) for k in keys])
        tangents = {k: mi.Float(rng_t.normal(size=dr.width(field.params[k])).astype(np.float32)) for k in keys}
        for k in keys:
            dr.set_grad(field.params[k], tangents[k])
        dr.forward_to(f)
        return np.array(dr.detach(f)), np.array(dr.grad(f))

    # ridge lanes: interior points with random ray directions; with a face tolerance of 0.5 m
    # about half of them lie on a ridge, most between faces of different axes
    with dr.suspend_grad():
        box = InstanceField.view_lanes(field.decode(), inst, t)
        interior = np.flatnonzero(np.array(box_sdf_local(box.to_local(p), box.half)) < 0.0)[::2]
    lanes = mi.UInt32(interior.astype(np.uint32))
    dirs = rng.normal(size=(len(interior), 3))
    ridge = (lanes, vec(dirs / np.linalg.norm(dirs, axis=1, keepdims=True)), 0.5)
    if kinks:
        lam = rng.uniform(0.0, 1.0, len(interior))
        lam[::2] = -1.0
        ridge = (*ridge, mi.Float(lam.astype(np.float32)))

    def closed(dec, weights):
        return field.lane_sdfs(dec, p, t, inst, weights, reach=reach, ridge=ridge, grad_reach=grad_reach)

    def plain(dec, weights):
        # far lanes (box SDF beyond the reach, where the residual cannot bring it back) keep
        # the detached box SDF alone
        f = field.lane_sdfs_ad(dec, p, t, inst, weights, reach)
        with dr.suspend_grad():
            box = InstanceField.view_lanes(dec, inst, t)
            f_box = box_sdf_local(box.to_local(p), box.half)
            far = f_box > (max(grad_reach, reach) if residual else grad_reach)
        return dr.select(far, f_box, f) + field.ridge_correction(dec, p, t, inst, ridge)

    for mode in ("reverse", "forward"):
        rng_t = np.random.default_rng(14)
        f1, g1 = run(closed, mode)
        rng_t = np.random.default_rng(14)
        f2, g2 = run(plain, mode)
        np.testing.assert_allclose(f1, f2, atol=1e-6)
        assert np.abs(g2).max() > 0.0
        np.testing.assert_allclose(g1, g2, rtol=2e-4, atol=2e-4 * np.abs(g2).max())


def test_softplus_sigmoid_exact_and_finite():
    x = dr.opaque(mi.Float, 0.0)
    dr.enable_grad(x)
    y = softplus(x)
    dr.backward(y)
    assert y[0] == pytest.approx(np.log(2.0), abs=1e-7)
    assert dr.grad(x)[0] == pytest.approx(0.5, abs=1e-7)
    assert sigmoid(mi.Float(0.0))[0] == 0.5
    for v in (1e4, -1e4):
        x = dr.opaque(mi.Float, v)
        dr.enable_grad(x)
        y1, y2 = softplus(x), sigmoid(x)
        dr.backward(y1 + y2)
        vals = [y1[0], y2[0], dr.grad(x)[0]]
        assert np.all(np.isfinite(vals)), vals
        assert y1[0] == pytest.approx(max(v, 0.0), rel=1e-6)
        assert y2[0] == pytest.approx(1.0 if v > 0 else 0.0, abs=1e-7)
    xs = np.linspace(-30, 30, 61)
    np.testing.assert_allclose(np.array(softplus(mi.Float(xs))), np.logaddexp(0.0, xs), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.array(sigmoid(mi.Float(xs))), 1.0 / (1.0 + np.exp(-xs)), rtol=1e-5, atol=1e-7)


def test_sigmoid_derivative_is_s_times_one_minus_s_at_zero_too():
    """A latent at the centre of its range is 0: its sigmoid must still pass a gradient (0.25)."""
    xs = np.array([-8.0, -1.0, 0.0, 0.5, 8.0])
    x = mi.Float(xs)
    dr.enable_grad(x)
    dr.backward(dr.sum(sigmoid(x)))
    s = 1.0 / (1.0 + np.exp(-xs))
    np.testing.assert_allclose(np.array(dr.grad(x)), s * (1.0 - s), rtol=1e-5, atol=1e-8)


def random_boxes(rng, n):
    centres = np.stack([rng.uniform(-20, 20, n), rng.uniform(0, 2, n), rng.uniform(5, 60, n)], 1)
    sizes = np.stack([rng.uniform(1.4, 2.4, n), rng.uniform(1.2, 2.5, n), rng.uniform(3.0, 6.5, n)], 1)
    yaws = rng.uniform(-np.pi + 0.01, np.pi - 0.01, n)
    return centres, sizes, yaws


def test_boxes_round_trip_in_physical_units():
    """The box properties come back from :meth:`InstanceField.boxes` as given (float32), and
    decode to half extents, the yaw's cosine and sine and the velocity, each box's own."""
    rng = np.random.default_rng(2)
    centres, sizes, yaws = random_boxes(rng, 7)
    vel = rng.normal(size=(7, 3))
    dyn = (rng.uniform(size=7) < 0.5).astype(float)
    field = make_field(centres, sizes, yaws, vel, dyn)
    out = field.boxes()
    np.testing.assert_allclose(out["centre"], centres, rtol=1e-6)
    np.testing.assert_allclose(out["size"], sizes, rtol=1e-6)
    np.testing.assert_allclose(out["yaw"], yaws, rtol=1e-6)
    np.testing.assert_allclose(out["velocity"], vel, rtol=1e-6)
    np.testing.assert_array_equal(out["dynamic"], dyn)
    dec = field.decode()
    np.testing.assert_allclose(np.stack([np.array(h) for h in dec.half], 1), 0.5 * sizes, rtol=1e-6)
    np.testing.assert_allclose(np.array(dec.cos), np.cos(yaws), atol=1e-6)
    np.testing.assert_allclose(np.array(dec.sin), np.sin(yaws), atol=1e-6)


def test_residual_bounded_and_differentiable():
    rng = np.random.default_rng(3)
    centres, sizes, yaws = random_boxes(rng, 2)
    field = make_field(centres, sizes, yaws, residual=True)
    rdf = field.residual
    for v in rdf.params.values():
        dr.enable_grad(v)
    w = field.residual_weights()
    assert w.shape == (ResidualConfig().num_mlp_params, 2)
    p = rng.uniform(-3, 3, (512, 3)).astype(np.float32)
    r = rdf.evaluate(w, 1, vec(p))
    vals = np.array(r)
    assert np.all(vals >= 0.0) and np.all(vals <= rdf.cfg.max_residual)
    assert vals.std() > 0.0  # it depends on the point
    dr.backward(dr.sum(r * r))
    g_emb = np.array(dr.grad(rdf.params["embedding"])).reshape(2, -1)
    assert np.all(np.isfinite(g_emb))
    assert np.abs(g_emb[1]).max() > 0.0          # instance 1's embedding gets a gradient
    assert np.abs(g_emb[0]).max() == 0.0         # instance 0 was not evaluated
    for i in range(rdf.num_hyper_layers):
        g = np.array(dr.grad(rdf.params[f"hyper_w{i}"]))
        assert np.all(np.isfinite(g)) and np.abs(g).max() > 0.0, i


def test_residual_added_only_near_the_box():
    centres, sizes, yaws = np.array([[0.0, 0.0, 10.0]]), np.array([[2.0, 1.5, 4.0]]), np.array([0.0])
    field = make_field(centres, sizes, yaws, residual=True)
    plain = make_field(centres, sizes, yaws)
    p = np.array([[0.0, 0.0, 10.0], [0.5, 0.2, 11.0], [30.0, 0.0, 10.0]], np.float32)
    t = mi.Float(np.zeros(3, np.float32))
    w = field.residual_weights()
    f_res = np.array(field.instance_sdfs(field.decode(), mi.Point3f(p.T), t, w, reach=1.0)[0])
    f_box = np.array(plain.instance_sdfs(plain.decode(), mi.Point3f(p.T), t)[0])
    d = f_res - f_box
    assert np.all(d[:2] > 0) and np.all(d[:2] <= 1.0)
    assert d[2] == 0.0  # far outside the enlarged box: skipped


def np_residual(rdf, k: int, p: np.ndarray) -> np.ndarray:
    """The residual of instance ``k`` written out in NumPy from the raw parameters (float64)."""
    cfg = rdf.cfg
    prm = {key: np.array(v, dtype=np.float64) for key, v in rdf.params.items()}
    x = prm["embedding"].reshape(rdf.n, cfg.embedding_dim)[k]
    dims = [cfg.embedding_dim] + [cfg.hyper_width] * cfg.hyper_layers + [cfg.num_mlp_params]

    def gelu(v):  # tanh approximation, as the module documents
        return 0.5 * v * (1.0 + np.tanh(np.sqrt(2.0 / np.pi) * (v + 0.044715 * v ** 3)))

    def norm(v, axis):
        m = v.mean(axis=axis, keepdims=True)
        return (v - m) / np.sqrt(((v - m) ** 2).mean(axis=axis, keepdims=True) + 1e-5)

    for i in range(len(dims) - 1):
        x = prm[f"hyper_w{i}"].reshape(dims[i + 1], dims[i]) @ x + prm[f"hyper_b{i}"]
        if i < len(dims) - 2:
            x = gelu(norm(x, 0))
    q = np.stack([np.abs(p[:, 0]), p[:, 1], p[:, 2]], 0) * cfg.input_scale  # (3, n)
    feats = []
    for c in q:
        for f in range(cfg.frequencies):
            feats += [np.sin(c * 2.0 ** f * np.pi), np.cos(c * 2.0 ** f * np.pi)]
    h = np.stack(feats, 0)
    off = 0
    shapes = cfg.mlp_shapes()
    for i, (o, fi) in enumerate(shapes):
        w = x[off:off + o * fi].reshape(o, fi)
        off += o * fi
        h = w @ h + x[off:off + o, None]
        off += o
        if i < len(shapes) - 1:
            h = gelu(norm(h, 0))
    return cfg.max_residual / (1.0 + np.exp(-(h[0] - cfg.shift)))


def test_batched_residual_matches_numpy_per_instance():
    """Groups of different sizes (padded to one bucket) give each instance its own MLP."""
    rng = np.random.default_rng(11)
    centres, sizes, yaws = random_boxes(rng, 3)
    field = make_field(centres, sizes, yaws, residual=True)
    rdf = field.residual
    for key in rdf.params:  # non-trivial weights so instances differ visibly
        rdf.params[key] = mi.Float(np.array(rdf.params[key]) * 3.0)
    w = field.residual_weights()
    pts = [rng.uniform(-2.5, 2.5, (n, 3)) for n in (5, 300, 37)]
    out = rdf.evaluate_grouped(w, [2, 0, 1], [vec(p) for p in pts])
    for k, p, r in zip([2, 0, 1], pts, out):
        assert dr.width(r) == len(p)
        np.testing.assert_allclose(np.array(r), np_residual(rdf, k, p), atol=2e-4)
    assert np.abs(np.array(out[1])[:37] - np_residual(rdf, 1, pts[1][:37])).max() > 1e-3


def test_bucket_width():
    from vsrd_plugins.sdf.mlp import MIN_BUCKET, bucket_width
    assert bucket_width(1) == MIN_BUCKET
    assert bucket_width(MIN_BUCKET + 1) == 2 * MIN_BUCKET
    assert bucket_width(4096) == 4096 and bucket_width(4097) == 8192


def test_residual_fused_forward_matches_tensor_mode():
    """Detached residual evaluations (searches, scans) run as one fused cooperative-vector
    kernel; the tensor-mode matmuls (the reference AD path) give the same residual."""
    from vsrd_plugins.sdf import ResidualField

    field = ResidualField(3, ResidualConfig())
    weights = field.generate_weights()
    rng = np.random.default_rng(5)
    points = mi.Vector3f(*[mi.Float(rng.uniform(-3.0, 3.0, 777).astype(np.float32)) for _ in range(3)])
    tensor = np.array(field.evaluate_tensor(weights, 1, points))
    with dr.suspend_grad():
        fused = np.array(field.evaluate_grouped(weights, [1], [points])[0])
    assert tensor.min() > 0.0 and np.ptp(tensor) > 1e-3  # a field that varies
    np.testing.assert_allclose(fused, tensor, atol=1e-6)


@pytest.mark.parametrize("which", ["both", "weights", "points"])
def test_fused_residual_derivatives_match_tensor_mode(which):
    """:class:`_FusedResidual`'s hand-written derivatives (reverse and forward mode, w.r.t. the
    hypernetwork's parameters and the points, the mirrored x included) equal Dr.Jit's AD through
    the tensor-mode MLP, also when only one of the two inputs carries a gradient."""
    from dataclasses import replace

    from vsrd_plugins.sdf import ResidualField

    cfg = ResidualConfig(seed=4)
    fields = {mode: ResidualField(3, replace(cfg, gradients=mode)) for mode in ("fused", "tensor")}
    rng = np.random.default_rng(8)
    scale = {key: float(rng.uniform(1.0, 3.0)) for key in fields["fused"].params}
    pts = [rng.uniform(-3.0, 3.0, (n, 3)).astype(np.float32) for n in (600, 41)]
    tangents = {key: rng.normal(size=dr.width(v)).astype(np.float32) for key, v in fields["fused"].params.items()}
    dp = [rng.normal(size=p.shape).astype(np.float32) for p in pts]
    cot = [rng.normal(size=len(p)).astype(np.float32) for p in pts]

    def run(field, mode):
        for key in field.params:  # larger weights: instances and layers differ visibly
            field.params[key] = mi.Float(np.array(field.params[key]) * scale[key])
            if which != "points":
                dr.enable_grad(field.params[key])
        points = [vec(p) for p in pts]
        if which != "weights":
            for p in points:
                dr.enable_grad(p)
        out = field.evaluate_grouped(field.generate_weights(), [2, 0], points)
        if mode == "reverse":
            dr.backward(sum(dr.sum(r * mi.Float(c)) for r, c in zip(out, cot)))
            grads = [np.array(dr.grad(field.params[k])) for k in field.params] if which != "points" else []
            grads += [np.array(dr.grad(p)).ravel() for p in points] if which != "weights" else []
        else:
            if which != "points":
                for key in field.params:
                    dr.set_grad(field.params[key], mi.Float(tangents[key]))
            if which != "weights":
                for p, d in zip(points, dp):
                    dr.set_grad(p, vec(d))
            dr.forward_to(*out)
            grads = [np.array(dr.grad(r)) for r in out]
        return [np.array(dr.detach(r)) for r in out], grads

    for mode in ("reverse", "forward"):
        fields = {m: ResidualField(3, replace(cfg, gradients=m)) for m in ("fused", "tensor")}
        (v_f, g_f), (v_t, g_t) = run(fields["fused"], mode), run(fields["tensor"], mode)
        for a, b in zip(v_f, v_t):
            np.testing.assert_allclose(a, b, atol=1e-6)
        assert len(g_f) == len(g_t) > 0
        for a, b in zip(g_f, g_t):
            assert np.abs(b).max() > 0.0
            np.testing.assert_allclose(a, b, atol=2e-5 * np.abs(b).max(), err_msg=f"{mode} {which}")


def test_residual_lattice_reproduces_quadratics():
    """:class:`ResidualLattice` (tricubic Catmull-Rom) reproduces a residual that is quadratic
    in ``(|x|, y, z)`` exactly between its nodes, the kink of the mirrored ``|x|`` included (the
    node at ``-h`` is replaced by the quadratic extrapolation), reads per instance, clamps to
    the border past the covered box and gives 0 on inactive lanes; checked against the closed
    form."""
    from vsrd_plugins.sdf import ResidualLattice
    rng = np.random.default_rng(8)
    extents, spacing = np.array([[1.3, 0.9, 2.1], [0.6, 1.4, 0.8]]), 0.17
    counts = ResidualLattice.node_counts(extents, spacing)
    coeffs = rng.normal(0.0, 0.05, (2, 10))

    def quad(k, x, y, z):
        c = coeffs[k].T  # (10,) for one instance, (10, n) per lane
        return (c[0] + c[1] * x + c[2] * y + c[3] * z + c[4] * x * x + c[5] * y * y + c[6] * z * z
                + c[7] * x * y + c[8] * y * z + c[9] * x * z)

    values = []
    for k in range(2):
        axes = [(np.arange(counts[k, a]) - 1.0) * spacing + (0.0 if a == 0 else -extents[k, a]) for a in range(3)]
        gx, gy, gz = np.meshgrid(*axes, indexing="ij")
        # the node at x = -h holds R(h) (the field's mirror symmetry), which the lookup must not read
        values.append(quad(k, np.abs(gx), gy, gz).ravel())
    sizes = counts.prod(axis=1)
    lattice = ResidualLattice(mi.Float(np.concatenate(values)), mi.UInt32([0, int(sizes[0])]),
                              tuple(mi.UInt32(counts[:, a].astype(np.uint32)) for a in range(3)),
                              (mi.Float([0.0, 0.0]), mi.Float(-extents[:, 1]), mi.Float(-extents[:, 2])),
                              mi.Float(1.0 / spacing), 2)
    inst = rng.integers(0, 2, 400)
    p = rng.uniform(-1.0, 1.0, (400, 3)) * extents[inst]
    p[:40, 0] = rng.uniform(-spacing, spacing, 40)  # the cells at the mirror plane
    got = np.array(lattice.residual(mi.UInt32(inst), vec(p)))
    np.testing.assert_allclose(got, quad(inst, np.abs(p[:, 0]), p[:, 1], p[:, 2]), atol=2e-6)
    # past the covered box: the border's value; an inactive lane or an invalid instance: 0
    far = np.array([[extents[0, 0] + 5.0, 0.0, 0.0]])
    border = quad(0, (counts[0, 0] - 3) * spacing, 0.0, 0.0)  # the last node a lookup reaches
    assert np.isfinite(np.array(lattice.residual(mi.UInt32([0]), vec(far)))).all()
    assert abs(float(np.array(lattice.residual(mi.UInt32([0]), vec(far)))[0]) - border) < 1e-5
    assert np.array(lattice.residual(mi.UInt32([2, 0]), vec(np.zeros((2, 3))), mi.Bool([True, False]))).tolist() == [0.0, 0.0]


def test_residual_lattice_of_the_field_matches_the_mlp():
    """:meth:`ResidualField.lattice` tabulates each instance's own MLP: at random points of
    each enlarged box the lookups agree with the MLP to 1.5 % of the field's range at the
    integrator's default spacing (0.35 rad of the encoding's highest frequency; measured 0.6 %
    with weights tripled from their initialisation), and 10x better at half the spacing
    (measured 13x)."""
    from vsrd_plugins.sdf import ResidualField
    rng = np.random.default_rng(9)
    cfg = ResidualConfig()
    field = ResidualField(2, cfg)
    for key in field.params:  # non-trivial weights so the field varies visibly
        field.params[key] = mi.Float(np.array(field.params[key]) * 3.0)
    weights = field.generate_weights()
    extents = np.array([[2.6, 1.7, 1.6], [1.9, 1.5, 1.4]])
    omega = np.pi * 2.0 ** (cfg.frequencies - 1) * cfg.input_scale
    inst = rng.integers(0, 2, 2000)
    p = rng.uniform(-1.0, 1.0, (2000, 3)) * extents[inst]
    with dr.suspend_grad():
        exact = np.concatenate([np.array(field.evaluate_grouped(weights, [k], [vec(p[inst == k])])[0])
                                for k in range(2)])
        order = np.concatenate([np.flatnonzero(inst == k) for k in range(2)])
        errors = []
        for spacing in (0.35 / omega, 0.175 / omega):
            got = np.array(field.lattice(weights, extents, spacing).residual(mi.UInt32(inst), vec(p)))[order]
            errors.append(np.abs(got - exact).max())
    span = np.ptp(exact)
    assert span > 0.03, span
    assert errors[0] <= 0.015 * span and errors[1] < 0.1 * errors[0], (errors, span)
