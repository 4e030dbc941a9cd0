"""Fuzz test of every documented property of ``vsrd_silhouette`` and ``sdf_tracer``.

Good values, in every accepted form (strings, numbers, three-tuples, Dr.Jit arrays and tensors,
``box_properties``), load and render finite labels (a partition of unity) or finite traces; a
bad value of any property (wrong type, wrong count, NaN or infinity, a negative or zero size, a
count out of range, ``near >= far``, an unknown sampling name, ...) fails to load with an error
that names the property.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties
from vsrd_plugins.silhouette.settings import INTERNAL

PLUGINS = ("vsrd_silhouette", "sdf_tracer")
#: Rays per rendered example, aimed at the boxes from the origin.
RAYS = 32
LABEL_TOL = 1e-4
FUZZ = settings(max_examples=60, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ----------------------------------------------------------------------------------------------
# values in every accepted form
# ----------------------------------------------------------------------------------------------


def as_form(values: np.ndarray, form: str):
    """``values`` (flat) as a property value of the given form."""
    if form == "string":
        return " ".join(f"{v:.9g}" for v in values)
    if form == "commas":
        return ", ".join(f"{v:.9g}" for v in values)
    if form == "float":
        return mi.Float(values.astype(np.float32).tolist())
    if form == "tensor":
        return mi.TensorXf(values.astype(np.float32).reshape(1, -1))
    if form == "tuple" and len(values) == 3:
        return tuple(float(v) for v in values)
    if form == "number" and len(values) == 1:
        return float(values[0])
    return " ".join(f"{v:.9g}" for v in values)


FORMS = st.sampled_from(["string", "commas", "float", "tensor", "tuple", "number"])


@st.composite
def boxes(draw) -> dict[str, np.ndarray]:
    """One or two boxes 6-20 m ahead (the first straight ahead), their parameters flat."""
    n = draw(st.integers(1, 2))
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 31 - 1)))
    centre = np.stack([rng.uniform(-3, 3, n), rng.uniform(-0.5, 1.0, n), rng.uniform(6, 20, n)], 1)
    centre[0, 0] = 0.0
    size = rng.uniform(0.05, 6.0, (n, 3))
    return {"centre": centre.ravel(), "size": size.ravel(), "yaw": rng.uniform(-10, 10, n),
            "velocity": rng.normal(0, 1, 3 * n), "dynamic": (rng.uniform(size=n) < 0.5).astype(float)}


@st.composite
def good_case(draw) -> tuple[str, dict, int]:
    """A plugin, a valid property dictionary (random forms, optional properties left out at
    random) and its box count."""
    plugin = draw(st.sampled_from(PLUGINS))
    b = draw(boxes())
    n = len(b["yaw"])
    if draw(st.booleans()):
        props = dict(box_properties(b["centre"].reshape(-1, 3), b["size"].reshape(-1, 3), b["yaw"],
                                    b["velocity"].reshape(-1, 3), b["dynamic"]))
    else:
        props = {k: as_form(v, draw(FORMS)) for k, v in b.items()
                 if k in ("centre", "size") or draw(st.booleans())}
    optional = {"residual": st.booleans(), "residual_seed": st.integers(0, 1000)}
    near = draw(st.floats(0.0, 1.0))
    if plugin == "vsrd_silhouette":
        optional.update(sampling=st.sampled_from(["adaptive", "dense"]), band_samples=st.integers(2, 24),
                        sharpness=st.floats(0.5, 1e4), temperature=st.floats(1e-3, 1.0), near=st.just(near),
                        far=st.floats(60.0, 200.0))
    else:
        optional.update(max_iterations=st.integers(1, 300), epsilon=st.floats(1e-7, 1e-3), near=st.just(near),
                        far=st.floats(60.0, 300.0))
    for name, strategy in optional.items():
        if draw(st.booleans()):
            props[name] = draw(strategy)
    return plugin, props, n


#: Per property, bad values (callables of the box count) and the property the error must name.
BAD = {
    "centre": [lambda n: "1 2", lambda n: " ".join(["nan"] * 3 * n), lambda n: "left right", lambda n: "1 2 inf"],
    "size": [lambda n: " ".join(["-1.5"] * 3 * n), lambda n: " ".join(["0"] * 3 * n), lambda n: "1 1",
             lambda n: " ".join(["nan"] * 3 * n), lambda n: "big"],
    "yaw": [lambda n: " ".join(["0.1"] * (n + 1)), lambda n: " ".join(["inf"] * n), lambda n: "north"],
    "velocity": [lambda n: " ".join(["0.1"] * (3 * n + 1)), lambda n: " ".join(["nan"] * 3 * n)],
    "dynamic": [lambda n: " ".join(["0.5"] * n), lambda n: " ".join(["1"] * (n + 2)), lambda n: "yes"],
    "residual": [lambda n: "maybe", lambda n: 2],
    "residual_seed": [lambda n: -1, lambda n: 1.5, lambda n: "lucky"],
}
BAD_SILHOUETTE = {
    "sampling": [lambda n: "fast", lambda n: 3],
    "band_samples": [lambda n: 1, lambda n: 2.5, lambda n: "many"],
    "sharpness": [lambda n: 0.0, lambda n: -10.0, lambda n: float("nan"), lambda n: "sharp"],
    "temperature": [lambda n: 0.0, lambda n: -0.1, lambda n: float("inf")],
    "near": [lambda n: -1.0, lambda n: float("nan"), lambda n: 500.0],
    "far": [lambda n: 0.0, lambda n: float("inf"), lambda n: -5.0],
}
BAD_TRACER = {
    "max_iterations": [lambda n: 0, lambda n: 2.5],
    "epsilon": [lambda n: 0.0, lambda n: -1e-5],
    "near": [lambda n: -1.0, lambda n: 1000.0],
    "far": [lambda n: 0.0, lambda n: float("nan")],
}


@st.composite
def bad_case(draw) -> tuple[str, dict, str]:
    """A plugin, a property dictionary with one bad value, and that property's name."""
    plugin, props, n = draw(good_case())
    table = {**BAD, **(BAD_SILHOUETTE if plugin == "vsrd_silhouette" else BAD_TRACER)}
    name = draw(st.sampled_from(sorted(table)))
    props = {k: v for k, v in props.items() if k not in ("near", "far")} if name in ("near", "far") else props
    props[name] = draw(st.sampled_from(table[name]))(n)
    return plugin, props, name


def load(plugin: str, props: dict):
    return mi.load_dict({"type": plugin, **props})


def error_line(exc: BaseException) -> str:
    """The plugin's own message: the last line of Mitsuba's wrapped error."""
    return str(exc).strip().splitlines()[-1]


# ----------------------------------------------------------------------------------------------
# the tests
# ----------------------------------------------------------------------------------------------


@FUZZ
@given(bad_case())
def test_bad_property_values_raise_an_error_naming_the_property(case):
    plugin, props, name = case
    with pytest.raises(Exception) as info:
        load(plugin, props)
    assert f"'{name}'" in error_line(info.value), (name, props[name], error_line(info.value))


@FUZZ
@given(good_case())
def test_good_property_values_render_finite_labels(case):
    plugin, props, n = case
    it = load(plugin, props)
    assert it.field.n == n
    rng = np.random.default_rng(0)
    target = it.boxes()["centre"][rng.integers(0, n, RAYS)] + rng.uniform(-0.5, 0.5, (RAYS, 3))
    d = target / np.linalg.norm(target, axis=1, keepdims=True)
    o = mi.Point3f(*[mi.Float(np.zeros(RAYS, np.float32)) for _ in range(3)])
    dirs = mi.Vector3f(*[mi.Float(d[:, j].astype(np.float32)) for j in range(3)])
    time = mi.Float(rng.uniform(-1, 1, RAYS).astype(np.float32))
    with dr.suspend_grad():
        if plugin == "vsrd_silhouette":
            labels = np.stack([np.array(x) for x in it.render_rays(o, dirs, time)])
            assert labels.shape == (n + 1, RAYS)
            assert np.all(np.isfinite(labels)) and np.all(labels >= -LABEL_TOL)
            np.testing.assert_allclose(labels.sum(0), 1.0, atol=LABEL_TOL)
        else:
            out = it.trace_rays(o, dirs, time)
            for key in ("t", "depth", "normal"):
                assert np.all(np.isfinite(np.array(out[key]))), key


@pytest.mark.parametrize("name", INTERNAL)
def test_internal_settings_are_not_properties(name):
    """Internal tuning given as a property says where it is set instead."""
    with pytest.raises(Exception) as info:
        load("vsrd_silhouette", {"centre": "0 0 8", "size": "2 1.5 4", name: 1})
    assert f"'{name}' is an internal setting" in error_line(info.value) and "integrator.settings" in error_line(info.value)


def test_lists_and_numpy_arrays_go_through_box_properties():
    """Mitsuba's dictionary parser refuses Python lists and NumPy arrays before any plugin sees
    them; ``box_properties`` turns them into strings that load to the same boxes."""
    centre, size = np.array([[0.0, 0.5, 8.0], [2.0, 0.5, 12.0]]), [[1.8, 1.5, 4.2], [2.0, 1.6, 4.6]]
    with pytest.raises(Exception):
        load("vsrd_silhouette", {"centre": centre, "size": size})
    it = load("vsrd_silhouette", box_properties(centre, size, yaw=(0.1, -0.2)))
    np.testing.assert_allclose(it.boxes()["centre"], centre, rtol=1e-6)
    np.testing.assert_allclose(it.boxes()["size"], size, rtol=1e-6)
    with pytest.raises(Exception, match="'yaw' has 3 values"):
        box_properties(centre, size, yaw=[0.1, 0.2, 0.3])


def test_traversed_parameters_of_the_wrong_width_are_refused():
    """A box parameter set through ``mi.traverse`` with the wrong number of values is refused
    at ``update()``, naming the parameter."""
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "vsrd_silhouette", "id": "vsrd",
                                                          **box_properties([[0, 0, 8]], [[2, 1.5, 4]], [0.0])}})
    params = mi.traverse(scene)
    params["vsrd.size"] = mi.Float([2.0, 1.5])
    with pytest.raises(Exception, match="parameter 'size' has 2 values"):
        params.update()
