"""Acceptance: a perturbed box is recovered from multi-view silhouettes through Mitsuba plumbing.

One box is rendered by ``vsrd_silhouette`` (adaptive sampling, no residual) from 8 perspective
sensors of a scene loaded with ``mi.load_dict``; their soft labels at the final sharpness are the
targets. The box is then perturbed (centre ~0.5 m, size ~15 %, yaw 15 degrees) through
``mi.traverse(scene)`` and only its box parameters are optimised with ``mi.ad.Adam`` on the BCE of
the rendered labels against the targets, under a sharpness schedule that starts blurred (wide
basin) and ends at the target's sharpness (unbiased optimum). The recovered box must overlap the
true one with 3D IoU >= 0.9.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.iou3d import iou3d
from vsrd_mi.optimise.losses import binary_cross_entropy, mean, to_float
from vsrd_mi.optimise.parameters import BOX_LATENTS, BoxLatents, BoxRanges
from vsrd_mi.scene.sensors import perspective_sensor

INTEGRATOR = "vsrd"
BOX_KEYS = BOX_LATENTS  # the optimised latents (box_dims, box_centre, box_yaw), decoded into the boxes
IOU_MIN = 0.9

TRUTH = Box3D(centre=np.array([0.4, 0.3, 14.0]), size=np.array([1.8, 1.55, 4.3]), yaw=0.4)
#: The initial box: centre moved by ~0.5 m, sizes scaled by ~15 %, yaw turned by 15 degrees.
CENTRE_OFFSET = np.array([0.35, -0.1, -0.34])
SIZE_SCALE = np.array([1.15, 0.87, 1.15])
YAW_OFFSET = np.radians(15.0)


@dataclass(frozen=True)
class Rig:
    """``views`` cameras on a circle of ``radius`` around the box, ``height`` above its centre."""

    views: int = 8
    radius: float = 9.0
    height: float = 2.5  # metres above the box centre (the scene frame is y-down)
    focal: float = 26.0  # pixels
    width: int = 32
    height_px: int = 24


@dataclass(frozen=True)
class Fit:
    """Optimisation schedule: ``1/s`` falls linearly from ``1/s_start`` to ``1/s_end`` over the
    first ``ramp`` fraction of the steps, then stays; learning rates per raw parameter (the
    decoded centre moves ~30 m and a half-size ~0.2 m per unit of its raw parameter)."""

    steps: int = 160
    s_start: float = 2.0
    s_end: float = 10.0
    ramp: float = 0.6
    lr_centre: float = 2e-3
    lr_dims: float = 8e-2
    lr_yaw: float = 1e-2
    lr_decay: float = 0.1  # final learning rate / initial
    bce_eps: float = 1e-6


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) at ``eye`` looking at ``target``."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def scene_description(box: Box3D, rig: Rig) -> dict:
    """Scene with the box in an adaptive ``vsrd_silhouette`` and ``rig.views`` sensors around it."""
    K = np.array([[rig.focal, 0.0, (rig.width - 1) / 2.0], [0.0, rig.focal, (rig.height_px - 1) / 2.0],
                  [0.0, 0.0, 1.0]])
    desc = {"type": "scene",
            "integrator": {"type": "vsrd_silhouette", "id": INTEGRATOR, "sampling": "adaptive",
                           "residual": False,
                           **box_properties(box.centre[None], box.size[None], np.array([box.yaw]))}}
    for i in range(rig.views):
        a = 2.0 * np.pi * i / rig.views
        eye = box.centre + np.array([rig.radius * np.sin(a), -rig.height, rig.radius * np.cos(a)])
        desc[f"view_{i}"] = perspective_sensor(K, look_at(eye, box.centre), (rig.width, rig.height_px), 0)
    return desc


def sensor_rays(scene: mi.Scene, rig: Rig) -> tuple[mi.Point3f, mi.Vector3f, mi.Float]:
    """One ray through every pixel centre of every sensor (Dr.Jit-owned copies, see to_float)."""
    u, v = np.meshgrid(np.arange(rig.width), np.arange(rig.height_px))
    film = mi.Point2f(to_float((u.ravel() + 0.5) / rig.width), to_float((v.ravel() + 0.5) / rig.height_px))
    o, d, t = [], [], []
    for sensor in scene.sensors():
        ray, _ = sensor.sample_ray(sensor.shutter_open(), 0.5, film, mi.Point2f(0.5, 0.5))
        o.append(np.array(ray.o))
        d.append(np.array(ray.d))
        t.append(np.broadcast_to(np.array(ray.time).ravel(), (dr.width(ray.d.x),)))
    o, d, t = (np.concatenate(x, axis=-1) for x in (o, d, t))
    return (mi.Point3f(*[to_float(c) for c in o]), mi.Vector3f(*[to_float(c) for c in d]), to_float(t))


def write_box(params: mi.SceneParameters, latents: BoxLatents, values: dict) -> None:
    """Decode the latent ``values`` into the integrator's box parameters."""
    for key, value in latents.decode(values).items():
        params[f"{INTEGRATOR}.{key}"] = value
    params.update()


def current_box(scene: mi.Scene) -> Box3D:
    b = scene.integrator().boxes()
    return Box3D(b["centre"][0], b["size"][0], float(b["yaw"][0]))


def inv_sharpness(fit: Fit, step: int) -> float:
    x = min(step / max(fit.ramp * fit.steps, 1.0), 1.0)
    return (1.0 - x) / fit.s_start + x / fit.s_end


def test_perturbed_box_is_recovered():
    rig, fit = Rig(), Fit()
    scene = mi.load_dict(scene_description(TRUTH, rig))
    integrator = scene.integrator()
    params = mi.traverse(scene)
    rays = sensor_rays(scene, rig)

    integrator.set_schedule(fit.s_end, 1.0 / fit.s_end)
    with dr.suspend_grad():
        target = integrator.render_rays(*rays)[0]
        dr.eval(target)
    coverage = float((np.array(target) > 0.5).mean())
    assert 0.05 < coverage < 0.6, coverage  # the box is in view and not filling the images

    start = Box3D(TRUTH.centre + CENTRE_OFFSET, TRUTH.size * SIZE_SCALE, TRUTH.yaw + YAW_OFFSET)
    latents = BoxLatents(BoxRanges(), 1)
    initial = latents.initial(start.centre[None], start.size[None], np.array([start.yaw]), np.zeros((1, 3)))
    write_box(params, latents, initial)
    iou_start = iou3d(current_box(scene), TRUTH)
    assert iou_start < 0.6, iou_start  # the perturbation is substantial

    opt = mi.ad.Adam(lr=fit.lr_dims, params={k: initial[k] for k in BOX_KEYS})
    base_lr = {BOX_KEYS[0]: fit.lr_dims, BOX_KEYS[1]: fit.lr_centre, BOX_KEYS[2]: fit.lr_yaw}
    losses = []
    for step in range(fit.steps):
        s = 1.0 / inv_sharpness(fit, step)
        integrator.set_schedule(s, 1.0 / s)
        decay = fit.lr_decay ** (step / fit.steps)
        opt.set_learning_rate({k: lr * decay for k, lr in base_lr.items()})
        write_box(params, latents, {k: opt[k] for k in BOX_KEYS})
        label = integrator.render_rays(*rays)[0]
        loss = mean(binary_cross_entropy(label, target, fit.bce_eps))
        dr.backward(loss)
        opt.step()
        losses.append(float(loss[0]))
    write_box(params, latents, {k: opt[k] for k in BOX_KEYS})

    final = current_box(scene)
    iou = iou3d(final, TRUTH)
    print(f"3D IoU {iou_start:.3f} -> {iou:.3f}; loss {losses[0]:.4f} -> {losses[-1]:.4f}; "
          f"centre {final.centre.round(3)} size {final.size.round(3)} yaw {final.yaw:.3f}")
    assert np.all(np.isfinite(losses))
    assert iou >= IOU_MIN, (iou, final)
