"""Numerical stress suite: random boxes and cameras through both integrators.

Every hypothesis example is one scene of :data:`N_INST` boxes and :data:`CAMERAS` cameras of
:data:`RAYS_PER_CAMERA` rays each; a camera with its rays is one *case*, and the rays of all
cases of an example go through the integrator in one launch (fixed shapes: the kernels compile
once and thousands of cases stay cheap). The examples cover sharpness ``s`` up to 1e4, cameras
inside boxes, rays in a face plane, along an edge and through a corner (grazing), boxes from 1 cm
to 20 m, centres at the edges of the optimiser's ranges, yaws of 0, 1e-9 and far outside
(-pi, pi], moving boxes at large frame offsets, boxes at 100 m, rays aimed away from every box
and an instance that no ray comes near. Checked: labels finite, in [0, 1], summing with the background
to 1, and finite gradients of a random-weighted loss w.r.t. every box parameter and, with the
residual on, every residual parameter; for ``sdf_tracer`` finite, consistent outputs.

Profiles (``@settings(derandomize=True, database=None, deadline=None)``: reproducible):

* default: :data:`DEFAULT_EXAMPLES` examples in total, split over the tests by :data:`SHARES`;
* full (``-m slow``, or ``VSRD_STRESS_EXAMPLES=N`` for the default tests): at least
  :data:`FULL_EXAMPLES` examples (``N`` when larger).

The end of the file checks the optimiser's NaN guard: a non-finite loss or gradient raises
:class:`OptimisationError`, and a batch run records the target as failed.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties
from vsrd_plugins.silhouette import VSRDSilhouetteIntegrator
from vsrd_plugins.tracer import SDFTracerIntegrator
from vsrd_mi.bench.measure import new_kernels
from vsrd_mi.bench.scenes import BOX_KEYS
from vsrd_mi.optimise.losses import to_float

#: Boxes per scene, cameras (cases) per example, rays per camera: fixed, so kernels compile once.
N_INST = 3
CAMERAS = 8
RAYS_PER_CAMERA = 32
N_RAYS = CAMERAS * RAYS_PER_CAMERA

#: Examples of the default run (all stress tests together) and the minimum of the full run.
DEFAULT_EXAMPLES = 300
FULL_EXAMPLES = 10_000
#: Environment variable selecting the full run for the default tests (its value: total examples).
EXAMPLES_ENV = "VSRD_STRESS_EXAMPLES"
#: Share of the examples per test (by cost: a dense or residual launch costs more).
SHARES = {"adaptive": 0.5, "adaptive_residual": 0.15, "dense": 0.15, "tracer": 0.2}

#: Label range / partition-of-unity tolerance (float32 sums of a few hundred weights).
LABEL_TOL = 1e-5
#: Box sizes (m) of the small and the large extremes: far below and above a car's, up to below a
#: sample spacing and around the camera.
SMALL_SIZES = (0.01, 0.05, 0.2, 1.0)
LARGE_SIZES = (5.4, 7.2, 12.0, 20.0)
#: Box sizes (m) of an ordinary box: the optimiser's latent range (vsrd_mi.optimise.parameters).
SIZE_RANGE = ((1.1, 1.0, 2.2), (2.7, 3.3, 7.2))
#: Centre coordinates (m) at the edges of the optimiser's range, per axis y and z.
CENTRE_EDGES = {1: (-5.0, 8.0), 2: (-5.0, 110.0)}
#: Yaws (rad): 0, tiny, and far outside (-pi, pi].
YAW_EXTREMES = (0.0, 1e-9, 3.0 * np.pi, 1e3)
#: Where an instance that no ray may approach is parked (static).
HIDDEN_CENTRE = (-55.0, 7.0, -3.0)
CAMERA_KINDS = ("outside", "inside", "face", "edge", "corner", "away", "random")


def examples(test: str, full: bool) -> int:
    """Examples of ``test`` in the default or the full profile (see the module docstring)."""
    env = int(os.environ.get(EXAMPLES_ENV, "0") or 0)
    total = max(FULL_EXAMPLES, env) if full else (env or DEFAULT_EXAMPLES)
    return max(1, round(total * SHARES[test]))


def stress(test: str, full: bool):
    return settings(max_examples=examples(test, full), derandomize=True, database=None,
                    deadline=None, print_blob=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


PROFILES = [pytest.param(False, id="default"), pytest.param(True, id="full", marks=pytest.mark.slow)]


def run_stress(test: str, full: bool, check, integrator) -> None:
    """Run ``check(integrator, knobs)`` on the examples of ``test`` in the chosen profile."""

    @stress(test, full)
    @given(scene_knobs)
    def run(knobs):
        check(integrator, knobs)

    run()


# ----------------------------------------------------------------------------------------------
# random scenes
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InstanceKnobs:
    """How one box is drawn: size / centre / yaw modes (see :func:`instance_knobs`)."""

    dims: str  # random | lo | hi | mixed (sizes of SMALL_SIZES / LARGE_SIZES, per axis for mixed)
    extreme: int  # index into SMALL_SIZES and LARGE_SIZES
    centre: str  # near | far (z 90-110 m) | bound (y or z at an edge of CENTRE_EDGES)
    yaw: float | None  # None: a random angle; else one of YAW_EXTREMES
    dynamic: bool


@dataclass(frozen=True)
class SceneKnobs:
    """One example: a NumPy seed for the bulk numbers plus the structured extremes."""

    seed: int
    sharpness: float
    temperature: float
    max_time: float
    instances: tuple[InstanceKnobs, ...]
    hidden: bool
    cameras: tuple[str, ...]


def log_uniform(lo: float, hi: float, ends: tuple[float, ...]):
    return st.one_of(st.sampled_from(ends),
                     st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0 ** e)))


instance_knobs = st.builds(
    InstanceKnobs,
    dims=st.sampled_from(["random", "random", "lo", "hi", "mixed"]),
    extreme=st.integers(0, len(SMALL_SIZES) - 1),
    centre=st.sampled_from(["near", "near", "far", "bound"]),
    yaw=st.one_of(st.none(), st.sampled_from(YAW_EXTREMES)),
    dynamic=st.booleans())

scene_knobs = st.builds(
    SceneKnobs,
    seed=st.integers(0, 2 ** 31 - 1),
    sharpness=log_uniform(1.0, 1e4, (1.0, 10.0, 1e4)),
    temperature=log_uniform(1e-3, 1.0, (1e-3, 1.0)),
    max_time=st.sampled_from([0.0, 2.0, 20.0]),
    instances=st.tuples(*[instance_knobs] * N_INST),
    hidden=st.booleans(),
    cameras=st.tuples(*[st.sampled_from(CAMERA_KINDS)] * CAMERAS))


def rot_y(c: float, s: float) -> np.ndarray:
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def box_parameters(k: SceneKnobs, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The box parameters of one example (flat, as ``mi.traverse`` lists them)."""
    centres, sizes = np.zeros((N_INST, 3)), np.zeros((N_INST, 3))
    yaw, velocity, dynamic = np.zeros(N_INST), np.zeros((N_INST, 3)), np.zeros(N_INST)
    for i, kn in enumerate(k.instances):
        centres[i] = [rng.uniform(-25, 25), rng.uniform(-1.5, 3.0),
                      rng.uniform(90, 110) if kn.centre == "far" else rng.uniform(2.0, 40.0)]
        small, large = SMALL_SIZES[kn.extreme], LARGE_SIZES[kn.extreme]
        sizes[i] = {"random": rng.uniform(*SIZE_RANGE), "lo": np.full(3, small), "hi": np.full(3, large),
                    "mixed": np.where(rng.uniform(size=3) < 0.5, small, large)}[kn.dims]
        if kn.centre == "bound":
            axis = int(rng.integers(1, 3))  # y or z at an edge (x edges are +-60 m: beside the road)
            centres[i, axis] = rng.choice(CENTRE_EDGES[axis])
        yaw[i] = rng.uniform(-np.pi, np.pi) if kn.yaw is None else kn.yaw * rng.choice([-1.0, 1.0])
        if kn.dynamic:
            dynamic[i] = 1.0
            velocity[i] = rng.normal(0.0, 1.5, 3) * np.array([1.0, 0.2, 1.0])
    if k.hidden:
        centres[-1], dynamic[-1], velocity[-1] = HIDDEN_CENTRE, 0.0, 0.0
    return {"centre": centres.ravel(), "size": sizes.ravel(), "yaw": yaw, "velocity": velocity.ravel(),
            "dynamic": dynamic}


def decoded(field) -> list[dict]:
    """The boxes (float64) as the integrators see them."""
    b = field.boxes()
    return [{"centre": b["centre"][i], "half": 0.5 * b["size"][i], "yaw": b["yaw"][i],
             "velocity": b["velocity"][i] * b["dynamic"][i]} for i in range(len(b["yaw"]))]


def camera_rays(kind: str, box: dict, boxes: list[dict], time: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``RAYS_PER_CAMERA`` rays (origins, unit directions) of one camera of ``kind``."""
    n = RAYS_PER_CAMERA
    centre = box["centre"] + box["velocity"] * time
    half = box["half"]
    R = rot_y(np.cos(box["yaw"]), np.sin(box["yaw"]))

    def world(local):
        return centre + local @ R.T

    if kind == "outside":
        direction = rng.normal(size=3)
        origin = world(direction / np.linalg.norm(direction) * rng.uniform(2.0, 30.0) + half * np.sign(direction))
        o = np.repeat(origin[None], n, 0)
        d = world(rng.uniform(-1.2, 1.2, (n, 3)) * half) - o
    elif kind == "inside":
        o = np.repeat(world(rng.uniform(-0.95, 0.95, 3) * half)[None], n, 0)
        d = rng.normal(size=(n, 3))
    elif kind == "face":  # rays lying in the plane of one face of the box
        axis = rng.integers(3)
        local = rng.uniform(-1.5, 1.5, (n, 3)) * half
        local[:, axis] = rng.choice([-1.0, 1.0]) * half[axis]
        dl = rng.normal(size=(n, 3))
        dl[:, axis] = 0.0
        dl /= np.linalg.norm(dl, axis=1, keepdims=True)
        o, d = world(local - 10.0 * dl), dl @ R.T
    elif kind == "edge":  # rays running along an edge line of the box
        axis = rng.integers(3)
        local = np.sign(rng.normal(size=(n, 3))) * half
        sign = rng.choice([-1.0, 1.0], n)
        local[:, axis] = -sign * (half[axis] + rng.uniform(0.0, 10.0, n))
        dl = np.zeros((n, 3))
        dl[np.arange(n), axis] = sign
        o, d = world(local), dl @ R.T
    elif kind == "corner":  # from anywhere around exactly through a corner
        o = world(rng.normal(size=(n, 3)) * 8.0)
        d = world(np.sign(rng.normal(size=(n, 3))) * half) - o
    elif kind == "away":  # from beside the boxes, pointing away from every box centre
        o = world(rng.normal(size=(n, 3)) * 3.0 + half * 3.0)
        mean_centre = np.mean([b["centre"] + b["velocity"] * time for b in boxes], 0)
        d = (o - mean_centre) + rng.normal(0.0, 0.05, (n, 3))
    else:
        o = rng.uniform([-10, -3, -5], [10, 3, 40], (n, 3))
        d = rng.normal(size=(n, 3))
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 1e-9, d / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))
    return o, d


def keep_away_from(box: dict, o: np.ndarray, d: np.ndarray, radius: float) -> tuple[np.ndarray, bool]:
    """Directions turned so no ray comes within ``radius`` of the (static) box; False when an
    origin is itself that close (the box then is not hidden)."""
    v = box["centre"] - o
    if np.any(np.linalg.norm(v, axis=1) <= radius):
        return d, False
    t = np.sum(v * d, axis=1)
    closest = np.linalg.norm(v - np.maximum(t, 0.0)[:, None] * d, axis=1)
    return np.where((closest <= radius)[:, None], -d, d), True


@dataclass
class Rays:
    o: np.ndarray
    d: np.ndarray
    time: np.ndarray
    hidden: bool  # the last instance is out of every ray's reach

    def mitsuba(self):
        return (mi.Point3f(*[to_float(c) for c in self.o.T]), mi.Vector3f(*[to_float(c) for c in self.d.T]),
                to_float(self.time))


def set_scene(field, k: SceneKnobs, margin: float) -> Rays:
    """Load the example's boxes into ``field`` and draw its rays; ``margin``: how far beyond a
    box an integrator may look (its reach)."""
    rng = np.random.default_rng(k.seed)
    for key, v in box_parameters(k, rng).items():
        field.params[key] = to_float(v)
    boxes = decoded(field)
    targets = boxes[:-1] if k.hidden else boxes
    os_, ds, ts = [], [], []
    for kind in k.cameras:
        time = float(rng.uniform(-k.max_time, k.max_time))
        o, d = camera_rays(kind, targets[rng.integers(len(targets))], boxes, time, rng)
        os_.append(o)
        ds.append(d)
        ts.append(np.full(len(o), time))
    o, d = np.concatenate(os_), np.concatenate(ds)
    hidden = k.hidden
    if hidden:
        d, hidden = keep_away_from(boxes[-1], o, d, float(np.linalg.norm(boxes[-1]["half"])) + margin + 0.5)
    return Rays(o, d, np.concatenate(ts), hidden)


def make_integrator(cls, **props):
    """An integrator with :data:`N_INST` placeholder boxes (replaced by :func:`set_scene`)."""
    p = mi.Properties()
    centres = np.array([[0.0, 0.0, 10.0 + 5 * i] for i in range(N_INST)])
    for key, v in {**box_properties(centres, np.tile([1.8, 1.5, 4.2], (N_INST, 1)), np.zeros(N_INST),
                                    dynamic=np.ones(N_INST)), **props}.items():
        p[key] = v
    return cls(p)


# ----------------------------------------------------------------------------------------------
# vsrd_silhouette
# ----------------------------------------------------------------------------------------------


def check_silhouette(it: VSRDSilhouetteIntegrator, k: SceneKnobs) -> Rays:
    it.set_schedule(k.sharpness, k.temperature)
    margin = it.settings.reach / k.sharpness + it.field.residual_reach
    rays = set_scene(it.field, k, margin)
    params = {key: it.field.params[key] for key in BOX_KEYS}
    if it.field.use_residual:
        params.update({f"rdf_{key}": v for key, v in it.field.residual.params.items()})
    for key, v in params.items():
        dr.enable_grad(v)
    try:
        labels = it.render_rays(*rays.mitsuba())
        rng = np.random.default_rng(k.seed + 1)
        loss = mi.Float(0.0)
        for lab in labels:
            loss = loss + dr.sum(lab * to_float(rng.normal(size=N_RAYS)))
        dr.backward(loss, dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        vals = np.stack([np.array(dr.detach(x)) for x in labels])
        grads = {key: np.array(dr.grad(v)) for key, v in params.items()}
    finally:
        for key in BOX_KEYS:
            it.field.params[key] = dr.detach(it.field.params[key])
        if it.field.use_residual:
            for key, v in it.field.residual.params.items():
                it.field.residual.params[key] = dr.detach(v)
    where = f"s={k.sharpness:g} tau={k.temperature:g} cameras={k.cameras}"
    assert vals.shape == (N_INST + 1, N_RAYS)
    assert np.all(np.isfinite(vals)), f"non-finite labels ({where})"
    assert np.all(vals >= -LABEL_TOL) and np.all(vals <= 1.0 + LABEL_TOL), \
        f"labels outside [0, 1]: {vals.min()} {vals.max()} ({where})"
    np.testing.assert_allclose(vals.sum(0), 1.0, atol=LABEL_TOL, err_msg=where)
    for key, g in grads.items():
        assert g.shape == (dr.width(params[key]),)
        assert np.all(np.isfinite(g)), f"non-finite gradient of {key} ({where})"
    assert it.last_stats.get("rays", 0) <= N_RAYS  # padded single-ray groups count one ray
    event(f"hidden instance: {rays.hidden}")
    return rays


@pytest.fixture(scope="module")
def adaptive():
    return make_integrator(VSRDSilhouetteIntegrator)


@pytest.fixture(scope="module")
def adaptive_residual():
    return make_integrator(VSRDSilhouetteIntegrator, residual=True)


@pytest.fixture(scope="module")
def dense():
    it = make_integrator(VSRDSilhouetteIntegrator, sampling="dense")
    it.settings = replace(it.settings, coarse_samples=32, fine_samples=16)
    return it


@pytest.mark.parametrize("full", PROFILES)
def test_silhouette_adaptive_stress(adaptive, full):
    run_stress("adaptive", full, check_silhouette, adaptive)


@pytest.mark.parametrize("full", PROFILES)
def test_silhouette_adaptive_residual_stress(adaptive_residual, full):
    run_stress("adaptive_residual", full, check_silhouette, adaptive_residual)


@pytest.mark.parametrize("full", PROFILES)
def test_silhouette_dense_stress(dense, full):
    run_stress("dense", full, check_silhouette, dense)


# ----------------------------------------------------------------------------------------------
# sdf_tracer
# ----------------------------------------------------------------------------------------------


def inside_box(o: np.ndarray, time: np.ndarray, box: dict, margin: float) -> np.ndarray:
    """Whether points ``o`` at ``time`` lie inside ``box`` by more than ``margin``."""
    R = rot_y(np.cos(box["yaw"]), np.sin(box["yaw"]))
    local = (o - box["centre"] - time[:, None] * box["velocity"]) @ R
    return np.all(np.abs(local) < box["half"] - margin, axis=1)


def check_tracer(it: SDFTracerIntegrator, k: SceneKnobs) -> None:
    margin = it.settings.start_margin + it.field.residual_reach
    rays = set_scene(it.field, k, margin)
    out = {key: np.array(v) for key, v in it.trace_rays(*rays.mitsuba()).items()}
    where = f"cameras={k.cameras}"
    hit, inst, t, normal = out["hit"].astype(bool), out["instance"], out["t"], out["normal"]
    assert hit.shape == (N_RAYS,) and normal.shape == (3, N_RAYS)
    for key in ("t", "depth", "normal"):
        assert np.all(np.isfinite(out[key])), f"non-finite {key} ({where})"
    np.testing.assert_array_equal(hit, inst >= 0, err_msg=where)
    assert np.all((inst >= -1) & (inst < N_INST)), where
    assert np.all(t[hit] >= it.settings.near) and np.all(t[hit] <= it.settings.far), where
    assert np.all(t[~hit] == 0) and np.all(normal[:, ~hit] == 0), where
    np.testing.assert_allclose(np.linalg.norm(normal[:, hit], axis=0), 1.0, atol=1e-4, err_msg=where)
    # a ray starting inside a box (clear of its faces) hits at t = near; boxes are the surfaces
    # without residual, and the residual only moves the surface inwards by at most its reach
    boxes = decoded(it.field)
    inside = np.zeros(N_RAYS, dtype=bool)
    for box in boxes:
        inside |= inside_box(rays.o, rays.time, box, 1e-3 + it.field.residual_reach)
    assert np.all(hit[inside]) and np.all(t[inside] == it.settings.near), where
    if rays.hidden:
        assert not np.any(inst == N_INST - 1), where
    event(f"hidden instance: {rays.hidden}, rays inside a box: {int(inside.sum() > 0)}")


@pytest.fixture(scope="module")
def tracer():
    return make_integrator(SDFTracerIntegrator)


@pytest.mark.parametrize("full", PROFILES)
def test_tracer_stress(tracer, full):
    run_stress("tracer", full, check_tracer, tracer)


# ----------------------------------------------------------------------------------------------
# fixed shapes: fresh rays every call compile nothing new
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("residual", [False, True])
def test_fresh_rays_do_not_recompile(residual):
    """Rays that change every call (an optimisation step) reuse the compiled kernels.

    Two boxes 12 m apart; ``a`` rays aimed at the first, ``b`` at the second, the rest at the
    sky, with ``(a, b)`` new in every call: the band groups and the backward pass's gradient
    arrays change width each call. Dr.Jit's LLVM ``ReduceMode.Expand`` scatter-additions (the
    backward of a gather) baked those widths into kernels, so every call recompiled. The
    residual MLP's kernels are shaped by each instance's point-count bucket (a power of two):
    the counts keep every instance's band points (about 30 per ray) in (1024, 2048] and its
    scan points (5 per ray) in (128, 256]. ``a != b``: Dr.Jit evaluates arrays of equal width
    in one kernel, so equal counts fuse the two instances' kernels into a new one (the same
    holds for the two instances' points in the AD graph: with ``(44, 46)`` both had 159 after
    the chord grid came in, and their backward scatter-adds fused).
    """
    scene = {"centre": np.array([[-6.0, 0.5, 15.0], [6.0, 0.5, 15.0]]),
             "size": np.array([[1.8, 1.5, 4.2], [2.0, 1.6, 4.5]]), "yaw": np.array([0.3, -0.4])}
    p = mi.Properties()
    for key, v in {**box_properties(**scene), "residual": residual}.items():
        p[key] = v
    it = VSRDSilhouetteIntegrator(p)
    it.set_schedule(10.0, 0.1)
    rng = np.random.default_rng(0)
    counts = [(40, 50), (45, 40), (50, 38), (38, 42), (44, 47), (36, 48)]
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        misses, seen = [], set()
        for a, b in counts:
            aims = [scene["centre"][0] + rng.uniform(-0.8, 0.8, (a, 3)),
                    scene["centre"][1] + rng.uniform(-0.8, 0.8, (b, 3)),
                    np.column_stack([rng.uniform(-5, 5, N_RAYS - a - b), np.full(N_RAYS - a - b, -50.0),
                                     rng.uniform(5, 20, N_RAYS - a - b)])]
            d = np.concatenate(aims)
            rays = Rays(np.zeros((N_RAYS, 3)), d / np.linalg.norm(d, axis=1, keepdims=True), np.zeros(N_RAYS), False)
            dr.kernel_history()  # clear
            centre = it.field.params["centre"]
            dr.enable_grad(centre)
            labels = it.render_rays(*rays.mitsuba())
            dr.backward(dr.sum(labels[0] * labels[0] + labels[1]))
            grad = dr.grad(centre)
            dr.eval(grad)
            misses.append(new_kernels(seen))
            it.field.params["centre"] = dr.detach(centre)
            assert it.last_stats["rays"] == a + b
            assert np.all(np.isfinite(np.array(grad)))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert misses[2:] == [0] * (len(counts) - 2), misses


# ----------------------------------------------------------------------------------------------
# the optimiser never emits a NaN box
# ----------------------------------------------------------------------------------------------

SCENE_ROOT = os.path.join(os.path.dirname(__file__), "..", "scenes", "kitti360-synth")
TARGET_FRAME = 14


def quick_config():
    """A few cheap box-only steps (the failure paths, not the accuracy, are under test)."""
    from vsrd_mi.optimise.config import default_config
    return default_config().replace(steps=3, warmup_steps=3, rays_per_step=64, residual=False, init=False)


@pytest.fixture(scope="module")
def target_obs():
    from vsrd_mi.data.kitti360 import Sequence
    from vsrd_mi.data.observations import load_observations
    from vsrd_mi.data.selection import SelectionConfig, spec_for_frame
    seq = Sequence(SCENE_ROOT, 0)
    return load_observations(seq, spec_for_frame(seq, TARGET_FRAME, SelectionConfig()))


def poison_projection_loss(monkeypatch, at_call: int, kind: str) -> list[int]:
    """Make the projection loss non-finite (``kind='value'``) or give it an infinite gradient
    with a finite value (``kind='gradient'``: ``sqrt(x - x)`` at ``x`` = the first centre) on its
    ``at_call``-th call (1-based); returns the call counter."""
    from vsrd_mi.optimise import losses
    real = losses.projection_loss
    calls = [0]

    def poisoned(dec, *args, **kwargs):
        calls[0] += 1
        loss = real(dec, *args, **kwargs)
        if calls[0] == at_call:
            if kind == "value":
                loss = loss + dr.opaque(mi.Float, float("nan"))
            else:
                x = dec.centre[0] - dr.detach(dec.centre[0])
                loss = loss + dr.sum(dr.sqrt(x))  # value 0, derivative +inf
        return loss

    monkeypatch.setattr(losses, "projection_loss", poisoned)
    return calls


def test_non_finite_loss_raises(monkeypatch, target_obs):
    from vsrd_mi.optimise.optimiser import BoxOptimiser, OptimisationError
    from vsrd_mi.scene.initial import default_initial_boxes
    poison_projection_loss(monkeypatch, 2, "value")
    with pytest.raises(OptimisationError, match=f"target {TARGET_FRAME}: non-finite loss at step 1"):
        BoxOptimiser(target_obs, default_initial_boxes(target_obs), quick_config()).run()


def test_non_finite_gradient_in_last_step_emits_no_box(monkeypatch, target_obs):
    """An infinite gradient turns the boxes into NaN after the last loss was computed (finite):
    the result is refused rather than returned."""
    from vsrd_mi.optimise.optimiser import BoxOptimiser, OptimisationError
    from vsrd_mi.scene.initial import default_initial_boxes
    # two steps: the frozen box step runs Python (and so the poisoned loss) only while it
    # records, in its first two steps; later steps replay the recording
    cfg = quick_config().replace(steps=2)
    calls = poison_projection_loss(monkeypatch, cfg.steps, "gradient")
    opt = BoxOptimiser(target_obs, default_initial_boxes(target_obs), cfg)
    with pytest.raises(OptimisationError, match="non-finite box parameters"):
        opt.run()
    assert calls[0] == cfg.steps
    assert not np.all(np.isfinite(opt.integrator.boxes()["centre"]))


def test_batch_records_non_finite_target_as_failed(monkeypatch, tmp_path):
    from vsrd_mi.batch import TargetTask, run_batch
    from vsrd_mi.data.kitti360 import sequence_name
    from vsrd_mi.autolabel.job import process_target
    poison_projection_loss(monkeypatch, 1, "value")
    seq = sequence_name(0)
    task = TargetTask(root=os.path.abspath(SCENE_ROOT), sequence=seq, frame=TARGET_FRAME,
                      output_dir=str(tmp_path), config=quick_config().to_dict(), seed=0)
    summary = run_batch([task], process_target, progress=False)
    assert (summary.done, summary.failed, summary.skipped) == (0, 1, 0)
    assert summary.failed_targets == [f"{seq}/{TARGET_FRAME:010d}"] and summary.exit_code() == 1
    entry = json.loads((tmp_path / seq / "manifest.json").read_text())["targets"][f"{TARGET_FRAME:010d}"]
    assert entry["status"] == "failed" and entry["outputs"] == []
    assert entry["error"]["type"].endswith("OptimisationError")
    assert "non-finite loss at step 0" in entry["error"]["message"]
    assert not (tmp_path / seq / "labels").exists() and not (tmp_path / seq / "boxes").exists()


@pytest.mark.parametrize("field", ["cam_to_opt", "K"])
def test_non_finite_camera_is_refused_before_optimising(target_obs, field):
    """Observations built by hand (not through the validating loader) with a NaN pose or
    intrinsic are refused up front, naming the frame, instead of optimising towards NaN."""
    import dataclasses
    from vsrd_mi.optimise.optimiser import BoxOptimiser
    from vsrd_mi.scene.initial import default_initial_boxes
    bad = getattr(target_obs, field).copy()
    bad[2, 0, 1] = np.nan
    obs = dataclasses.replace(target_obs, **{field: bad})
    frame = int(obs.frames[2])
    with pytest.raises(ValueError, match=rf"target {TARGET_FRAME}: non-finite {field} of frame\(s\) \[{frame}\]"):
        BoxOptimiser(obs, default_initial_boxes(target_obs), quick_config())
