"""Fit two boxes to instance masks with plain Mitsuba 3 and ``vsrd_plugins``.

Needs only Mitsuba 3, Dr.Jit, NumPy and the ``vsrd_plugins`` folder (copy ``plugins/vsrd_plugins``
next to this script or onto ``PYTHONPATH``). Two boxes of known size and pose are rendered as
Mitsuba ``cube`` meshes from four cameras with Mitsuba's ``aov`` integrator (depth), which gives
each camera's instance masks (the nearest cube per sub-pixel, averaged over 4 x 4 sub-pixels).
The ``vsrd_silhouette`` integrator then holds two boxes placed off the truth (moved, turned,
resized); ``mi.render`` returns its soft instance labels as AOV channels (RGB, ``label_0``,
``label_1``, ``background``), and ``mi.ad.Adam`` fits the boxes' ``centre``, ``size`` and ``yaw``
(metres and radians, read through ``mi.traverse``) to the masks while the sharpness rises from
blurred to sharp. The last line printed is the fitted boxes' mean 3D IoU against the true ones.

    python examples/fit_boxes.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import drjit as dr
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

import vsrd_plugins  # noqa: E402  (after the variant: the integrators derive from mi.ad classes)

vsrd_plugins.register()

#: The true boxes (scene frame: x right, y down, z forward; sizes are full extents w, h, l).
TRUTH = {"centre": np.array([[-1.6, 0.0, 9.0], [1.9, -0.1, 11.5]]),
         "size": np.array([[1.8, 1.5, 4.2], [2.0, 1.7, 4.8]]),
         "yaw": np.array([0.35, -0.6])}
#: Where the fit starts: each box moved (m), turned (rad) and resized (factor).
START_SHIFT = np.array([[0.5, 0.15, -0.6], [-0.45, -0.1, 0.7]])
START_TURN = np.array([-0.25, 0.3])
START_SCALE = np.array([[1.15, 0.9, 0.85], [0.88, 1.1, 1.15]])
#: Cameras on a circle around the boxes (azimuths in rad), this far (m) and this high (y < 0 is up).
CAMERA_AZIMUTHS = (0.0, 1.2, 2.6, -1.4)
CAMERA_DISTANCE, CAMERA_HEIGHT = 13.0, -5.0
LOOK_AT = (0.0, 0.0, 10.0)
IMAGE = (64, 48)  # width, height of the training views
FOV_DEG = 45.0
SUPERSAMPLE = 4  # target masks: sub-pixels per pixel along each axis
#: Sharpness s (1/m) rises geometrically from blurred to sharp; the softmin temperature is 1/s.
S_START, S_END = 1.0, 30.0
#: Adam learning rates (per step: metres, metres, radians), decayed by LR_DECAY over the run.
LR = {"vsrd.centre": 0.03, "vsrd.size": 0.02, "vsrd.yaw": 0.02}
LR_DECAY = 0.1


def camera(azimuth: float, size: tuple[int, int]) -> dict:
    """A perspective camera on the circle around :data:`LOOK_AT`, y down in the image."""
    origin = [LOOK_AT[0] + CAMERA_DISTANCE * np.sin(azimuth), CAMERA_HEIGHT,
              LOOK_AT[2] - CAMERA_DISTANCE * np.cos(azimuth)]
    return {"type": "perspective", "fov": FOV_DEG,
            "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=list(LOOK_AT), up=[0, -1, 0]),
            "film": {"type": "hdrfilm", "width": size[0], "height": size[1], "rfilter": {"type": "box"}}}


def cube(centre, size, yaw) -> dict:
    """A Mitsuba ``cube`` mesh (the cube [-1, 1]^3) scaled, turned about +y and moved onto a box."""
    to_world = (mi.ScalarTransform4f().translate(list(map(float, centre)))
                @ mi.ScalarTransform4f().rotate([0, 1, 0], float(np.degrees(yaw)))
                @ mi.ScalarTransform4f().scale(list(map(float, 0.5 * np.asarray(size)))))
    return {"type": "cube", "to_world": to_world}


def instance_masks(boxes: dict, view: dict) -> np.ndarray:
    """``(N, H, W)`` fractions of each pixel covered by each box, nearest box first: each cube
    rendered alone with Mitsuba's depth AOV at :data:`SUPERSAMPLE` x the resolution, the nearest
    cube per sub-pixel, averaged per pixel."""
    width, height = view["film"]["width"], view["film"]["height"]
    fine = {**view, "film": {**view["film"], "width": width * SUPERSAMPLE, "height": height * SUPERSAMPLE}}
    depths = []
    for centre, size, yaw in zip(boxes["centre"], boxes["size"], boxes["yaw"]):
        scene = mi.load_dict({"type": "scene", "sensor": fine, "integrator": {"type": "aov", "aovs": "dd:depth"},
                              "box": cube(centre, size, yaw)})
        depth = np.array(mi.render(scene, spp=1))[..., 0]
        depths.append(np.where(depth > 0.0, depth, np.inf))
    depths = np.stack(depths)
    nearest, hit = np.argmin(depths, axis=0), np.isfinite(depths.min(axis=0))
    masks = np.stack([(nearest == k) & hit for k in range(len(depths))]).astype(np.float32)
    return masks.reshape(len(depths), height, SUPERSAMPLE, width, SUPERSAMPLE).mean(axis=(2, 4))


# ----------------------------------------------------------------------------------------------
# exact 3D IoU of boxes turned about the vertical axis
# ----------------------------------------------------------------------------------------------


def footprint(centre, size, yaw) -> np.ndarray:
    """The box's four corners in the ground plane (x, z), counter-clockwise in (x, z)."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = 0.5 * np.array([[-size[0], -size[2]], [size[0], -size[2]], [size[0], size[2]], [-size[0], size[2]]])
    # the yaw rotation R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]] restricted to (x, z)
    return np.stack([centre[0] + c * local[:, 0] + s * local[:, 1], centre[2] - s * local[:, 0] + c * local[:, 1]], 1)


def polygon_area(p: np.ndarray) -> float:
    """Signed area (shoelace); positive for counter-clockwise corners."""
    return 0.5 * float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))


def clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """The intersection of two convex counter-clockwise polygons (Sutherland-Hodgman)."""
    out = subject
    for a, b in zip(clipper, np.roll(clipper, -1, axis=0)):
        if len(out) == 0:
            break
        edge = b - a
        inside = [edge[0] * (p[1] - a[1]) - edge[1] * (p[0] - a[0]) >= 0.0 for p in out]
        kept = []
        for i, p in enumerate(out):
            q, q_inside = out[i - 1], inside[i - 1]
            if inside[i] != q_inside:  # the edge p-q crosses the clip line: keep the crossing
                d = p - q
                t = (edge[0] * (a[1] - q[1]) - edge[1] * (a[0] - q[0])) / (edge[0] * d[1] - edge[1] * d[0])
                kept.append(q + t * d)
            if inside[i]:
                kept.append(p)
        out = np.array(kept)
    return out


def iou3d(a: tuple, b: tuple) -> float:
    """Exact 3D IoU of two boxes ``(centre, size, yaw)`` turned about the vertical (y) axis:
    the ground-plane intersection (a convex polygon) times the vertical overlap."""
    pa, pb = footprint(*a), footprint(*b)
    pa, pb = (p if polygon_area(p) > 0 else p[::-1] for p in (pa, pb))
    inter = clip(pa, pb)
    ground = polygon_area(inter) if len(inter) >= 3 else 0.0
    (ca, sa, _), (cb, sb, _) = a, b
    vertical = max(0.0, min(ca[1] + 0.5 * sa[1], cb[1] + 0.5 * sb[1]) - max(ca[1] - 0.5 * sa[1], cb[1] - 0.5 * sb[1]))
    overlap = ground * vertical
    return overlap / (np.prod(sa) + np.prod(sb) - overlap)


def mean_iou(boxes: dict, truth: dict) -> float:
    return float(np.mean([iou3d((boxes["centre"][k], boxes["size"][k], boxes["yaw"][k]),
                                (truth["centre"][k], truth["size"][k], truth["yaw"][k]))
                          for k in range(len(truth["yaw"]))]))


# ----------------------------------------------------------------------------------------------
# the fit
# ----------------------------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=160)
    args = ap.parse_args()
    start_time = time.perf_counter()
    views = [camera(a, IMAGE) for a in CAMERA_AZIMUTHS]
    n = len(TRUTH["yaw"])
    targets = [mi.TensorXf(np.ascontiguousarray(instance_masks(TRUTH, v).transpose(1, 2, 0))) for v in views]

    start = {"centre": TRUTH["centre"] + START_SHIFT, "size": TRUTH["size"] * START_SCALE,
             "yaw": TRUTH["yaw"] + START_TURN}
    scene = mi.load_dict({"type": "scene", **{f"camera_{i}": v for i, v in enumerate(views)},
                          "integrator": {"type": "vsrd_silhouette", "id": "vsrd",
                                         **vsrd_plugins.box_properties(start["centre"], start["size"], start["yaw"])}})
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=1.0, params={k: params[k] for k in LR})
    print(f"start: mean 3D IoU {mean_iou(scene.integrator().boxes(), TRUTH):.3f}")
    for step in range(args.steps):
        x = step / max(args.steps - 1, 1)
        s = S_START * (S_END / S_START) ** x
        params["vsrd.sharpness"], params["vsrd.temperature"] = s, 1.0 / s
        opt.set_learning_rate({k: lr * LR_DECAY ** x for k, lr in LR.items()})
        params.update(opt)
        loss = mi.Float(0.0)
        for i, target in enumerate(targets):
            image = mi.render(scene, params, sensor=i, spp=1, seed=step)  # RGB, label_0, label_1, background
            loss += dr.mean(dr.square((image[:, :, 3:3 + n] - target).array)) / len(targets)
        dr.backward(loss)
        opt.step()
        if step % 40 == 0 or step == args.steps - 1:
            print(f"step {step:4d}  sharpness {s:5.1f}  loss {loss[0]:.5f}")
    params.update(opt)
    boxes = scene.integrator().boxes()
    for k in range(n):
        print(f"box {k}: centre {np.round(boxes['centre'][k], 3)} (true {TRUTH['centre'][k]}), "
              f"size {np.round(boxes['size'][k], 3)} (true {TRUTH['size'][k]}), "
              f"yaw {boxes['yaw'][k]:.3f} (true {TRUTH['yaw'][k]})")
    print(f"{time.perf_counter() - start_time:.1f} s")
    print(f"mean 3D IoU of the fitted boxes vs the true ones: {mean_iou(boxes, TRUTH):.3f}")


if __name__ == "__main__":
    main()
