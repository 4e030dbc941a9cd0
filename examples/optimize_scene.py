"""Fit the car boxes of the bundled scene with plain Mitsuba 3 (mi.traverse, mi.ad.Adam, mi.render).

The target frame is loaded as a Mitsuba scene (one sensor per frame, the ``vsrd_silhouette``
integrator holding one box per car), the ground-truth boxes are moved and turned, and their
centres and yaws (``--fit-size``: sizes too, perturbed first) are fitted to the instance masks of a
few views rendered at low resolution: the integrator writes one soft label per box as an AOV
channel of ``mi.render``. Velocities stay at ground truth. A car's silhouette is smaller than its
box's, so a box-only silhouette fit is biased (boxes shrink or move away; ``vsrd-mi autolabel``
adds the residual shape field and the 2D-box projection loss). Writes ``before.png`` and
``after.png`` (target view) and ``masks.png`` (its real masks) to ``--out``.

    python examples/optimize_scene.py --steps 100 --out example_out
"""

import argparse
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
from vsrd_mi.autolabel.visualise import (
    box_colours,
    colourise,
    downscaled_masks,
    scaled_intrinsics,
    scaled_size,
)
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.iou3d import iou3d
from vsrd_mi.optimise.losses import binary_cross_entropy, mean, to_float
from vsrd_mi.scene.builder import load_scene
from vsrd_mi.scene.sensors import perspective_sensor

ROOT = Path(__file__).resolve().parents[1] / "scenes" / "kitti360-synth"
#: Adam learning rates per box parameter (m, rad, m): about the step a box moves per iteration.
LR = {"vsrd.centre": 0.05, "vsrd.yaw": 0.02, "vsrd.size": 0.02}
LR_DECAY = 0.1  # final / initial learning rate
S_START, S_END, RAMP = 2.0, 10.0, 0.6  # sharpness (1/m) from blurred to sharp over 60 % of the steps
PERTURB = {"centre_m": 1.5, "yaw_rad": 0.3, "size_frac": 0.2}  # centre: std along x and z


def ground_truth(seq: Sequence, obs) -> list[Box3D]:
    """Ground-truth box of every target instance, in the scene (optimisation) frame."""
    gt = {b.instance_id: b.transformed(obs.cam_to_opt[0]) for b in seq.ground_truth(obs.target)}
    missing = [int(i) for i in obs.instance_ids if int(i) not in gt]
    if missing:
        raise SystemExit(f"{seq.boxes_path}: no ground-truth box for instances {missing}")
    return [gt[int(i)] for i in obs.instance_ids]


def perturb(boxes: list[Box3D], rng: np.random.Generator, size: bool) -> list[Box3D]:
    out = []
    for b in boxes:
        shift = rng.normal(0.0, PERTURB["centre_m"], 3) * np.array([1.0, 0.0, 1.0])
        scale = 1.0 + size * rng.uniform(-PERTURB["size_frac"], PERTURB["size_frac"], 3)
        yaw = b.yaw + rng.uniform(-PERTURB["yaw_rad"], PERTURB["yaw_rad"])
        out.append(Box3D(b.centre + shift, b.size * scale, yaw, b.velocity, b.dynamic, b.instance_id))
    return out


def set_boxes(params: mi.SceneParameters, boxes: list[Box3D]) -> None:
    """Write boxes into the integrator's parameters (metres, radians) through ``mi.traverse``."""
    params["vsrd.centre"] = to_float([b.centre for b in boxes])
    params["vsrd.size"] = to_float([b.size for b in boxes])
    params["vsrd.yaw"] = to_float([b.yaw for b in boxes])
    params["vsrd.velocity"] = to_float([b.velocity for b in boxes])
    params["vsrd.dynamic"] = to_float([float(b.dynamic) for b in boxes])
    params.update()


def current_boxes(scene: mi.Scene, like: list[Box3D]) -> list[Box3D]:
    b = scene.integrator().boxes()
    return [Box3D(b["centre"][n], b["size"][n], b["yaw"][n], o.velocity, o.dynamic, o.instance_id)
            for n, o in enumerate(like)]


def sensor(obs, i: int, scale: float) -> mi.Sensor:
    """Frame ``i``'s camera with its image resized by ``scale``."""
    return mi.load_dict(perspective_sensor(scaled_intrinsics(obs.K[i], scale), obs.cam_to_opt[i],
                                           scaled_size(obs.image_size, scale), int(obs.dt[i])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", default=str(ROOT))
    ap.add_argument("--frame", type=int, default=3, help="target frame")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--views", type=int, default=4, help="frames rendered per step (target + sources)")
    ap.add_argument("--scale", type=float, default=0.125, help="training render scale of the images")
    ap.add_argument("--preview-scale", type=float, default=0.5, help="scale of before/after/masks.png")
    ap.add_argument("--fit-size", action="store_true", help="perturb and fit the box sizes too")
    ap.add_argument("--out", default="example_out")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    scene, obs = load_scene(args.root, 0, args.frame)  # one sensor per frame; boxes at a default guess
    params = mi.traverse(scene)
    truth = ground_truth(Sequence(args.root, 0), obs)
    start = perturb(truth, np.random.default_rng(args.seed), args.fit_size)
    set_boxes(params, start)

    # low-resolution training views (target + evenly spread frames); their masks are the targets
    picks = np.unique(np.linspace(0, obs.num_frames - 1, args.views).round().astype(int))
    size = scaled_size(obs.image_size, args.scale)
    views = [sensor(obs, int(i), args.scale) for i in picks]
    targets = [to_float(downscaled_masks(obs.masks[i], size).transpose(1, 2, 0)) for i in picks]  # (h, w, N)
    n = obs.num_instances
    preview = sensor(obs, 0, args.preview_scale)
    mi.util.write_bitmap(str(out / "before.png"), mi.render(scene, sensor=preview, spp=1)[:, :, :3])
    masks = downscaled_masks(obs.masks[0], scaled_size(obs.image_size, args.preview_scale))
    mi.util.write_bitmap(str(out / "masks.png"), colourise(masks, box_colours(n)))
    iou_before = [iou3d(b, t) for b, t in zip(current_boxes(scene, start), truth)]

    lrs = {k: v for k, v in LR.items() if args.fit_size or k != "vsrd.size"}
    opt = mi.ad.Adam(lr=1.0, params={k: params[k] for k in lrs})
    for step in range(args.steps):
        x = step / max(args.steps - 1, 1)
        r = min(x / RAMP, 1.0)
        s = 1.0 / ((1.0 - r) / S_START + r / S_END)
        params["vsrd.sharpness"], params["vsrd.temperature"] = s, 1.0 / s
        opt.set_learning_rate({k: lr * LR_DECAY ** x for k, lr in lrs.items()})
        params.update(opt)
        loss = mi.Float(0.0)
        for view, target in zip(views, targets):
            img = mi.render(scene, params, sensor=view, spp=1, seed=step)  # RGB, label_0..N-1, background
            loss += mean(binary_cross_entropy(img[:, :, 3:3 + n].array, target, 1e-6)) / len(views)
        dr.backward(loss)
        opt.step()
        if step % 20 == 0 or step == args.steps - 1:
            print(f"step {step:4d}  sharpness {s:5.2f}  loss {loss[0]:.4f}")
    params.update(opt)

    mi.util.write_bitmap(str(out / "after.png"), mi.render(scene, sensor=preview, spp=1)[:, :, :3])
    iou_after = [iou3d(b, t) for b, t in zip(current_boxes(scene, start), truth)]
    for b, a, z in zip(truth, iou_before, iou_after):
        print(f"instance {b.instance_id}: 3D IoU {a:.3f} -> {z:.3f}")
    print(f"mean 3D IoU vs ground truth: {np.mean(iou_before):.3f} -> {np.mean(iou_after):.3f}")


if __name__ == "__main__":
    main()
