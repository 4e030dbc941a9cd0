"""Visual checks of one optimised target (``vsrd-mi autolabel --vis``).

:func:`write_visuals` writes, under ``OUT/<sequence>/vis/<target %010d>/``:

* ``boxes_target.png``: the 12 edges of every optimised box (near-plane clipped) projected onto
  the target image through the camera's full pose (pitch and roll included), one colour per box,
  labelled ``instance: confidence``;
* ``boxes_sources.png``: the same over every source image (boxes moved to the source's time and
  camera), as a downscaled contact sheet;
* ``masks.png``: per row (target, then a few sources) the real instance masks beside the soft
  labels the optimised scene renders (the integrator's ``render_rays``, reduced resolution), with
  the soft IoU of the two;
* ``bev.png``: bird's-eye view of the optimisation frame (x right, z up the image): optimised
  boxes in their colours, ground-truth boxes in white when the dataset has them;
* ``loss.png``: the loss history (total, projection, silhouette, eikonal, init) against the step;
* ``meshes/instance_<id>.ply``: each instance's SDF (box, plus the residual field when it is on)
  at the target time, by marching cubes, in the optimisation frame.

Box ``n`` has colour ``instance_colours(N)[n]`` everywhere (the integrator's own colours), and
the real mask drawn in that colour is the instance the optimiser matched to box ``n``.

Visuals must never cost a target its labels: every part runs on its own and a failing part becomes
a warning in the returned :class:`VisualReport` (the caller writes it into the target's JSON).
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import drjit as dr
import mitsuba as mi
import numpy as np
from vsrd_plugins.silhouette import instance_colours

from ..batch.atomic import atomic_write_bytes
from ..data.kitti360 import Sequence as KittiSequence
from ..data.observations import Observations
from ..geometry.boxes import BOX_EDGES, Box3D
from ..geometry.camera import NEAR_PLANE, box_to_2d, project, transform_points
from ..geometry.iou3d import bev_footprint
from ..optimise.losses import to_float
from ..optimise.optimiser import BoxOptimiser, OptimisationResult
from ..scene.sensors import pixel_rays

log = logging.getLogger(__name__)

RGB = tuple[int, int, int]

#: Colours (RGB) of the bird's-eye view.
BEV_BACKGROUND: RGB = (24, 24, 24)
BEV_GRID: RGB = (64, 64, 64)
BEV_CAMERA: RGB = (150, 150, 150)
BEV_GT: RGB = (255, 255, 255)
#: Caption colour (RGB) and its dark outline.
TEXT: RGB = (255, 255, 255)
TEXT_SHADOW: RGB = (0, 0, 0)
#: Caption colour in the bird's-eye view: darker than :data:`BEV_GT`, so no caption pixel reads as GT.
BEV_TEXT: RGB = (210, 210, 210)
#: Loss-history series plotted, in this order (keys of ``OptimisationResult.loss_history``).
LOSS_SERIES = ("total", "projection", "silhouette", "eikonal", "init")


@dataclass(frozen=True)
class VisualConfig:
    """Sizes and resolutions of the visual outputs."""

    #: Projected boxes: edge thickness (px) and caption font scale.
    edge_thickness: int = 2
    font_scale: float = 0.5
    #: Source contact sheet: image scale and number of columns.
    sheet_scale: float = 0.5
    sheet_columns: int = 2
    #: Soft-mask comparison: render scale (of the image size) and source frames shown.
    mask_scale: float = 0.25
    mask_sources: int = 3
    #: Bird's-eye view: pixels per metre, margin around the boxes (m), grid spacing (m), and the
    #: largest region shown (m): lateral ``|x|``, forward ``z`` range.
    bev_px_per_m: float = 10.0
    bev_margin: float = 5.0
    bev_grid: float = 10.0
    bev_max_lateral: float = 40.0
    bev_forward: tuple[float, float] = (-10.0, 80.0)
    bev_box_thickness: int = 2
    #: Loss plot size (inches) and resolution.
    loss_figsize: tuple[float, float] = (8.0, 4.5)
    loss_dpi: int = 100
    #: Marching cubes: grid cells along the longest side of the padded box, and padding (cells)
    #: around the box so the surface closes inside the grid.
    mesh_cells: int = 48
    mesh_pad_cells: int = 2


@dataclass
class VisualReport:
    """What :func:`write_visuals` wrote and what went wrong (nothing raised)."""

    files: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: Soft IoU of rendered vs real masks per frame shown in ``masks.png``.
    mask_iou: dict[int, float] = field(default_factory=dict)
    #: Marching-cubes grid spacing (m) per instance id.
    mesh_spacing: dict[int, float] = field(default_factory=dict)

    def to_dict(self, relative_to: Path | None = None) -> dict:
        """JSON-ready summary; file paths relative to ``relative_to`` when given."""
        files = [str(p.relative_to(relative_to) if relative_to else p) for p in self.files]
        return {"files": files, "warnings": list(self.warnings),
                "mask_iou": {str(k): v for k, v in self.mask_iou.items()},
                "mesh_spacing": {str(k): v for k, v in self.mesh_spacing.items()}}


# ----------------------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------------------


def box_colours(n: int) -> list[RGB]:
    """RGB uint8 colour of each of ``n`` boxes (the silhouette integrator's colours)."""
    return [tuple(int(round(255 * c)) for c in rgb) for rgb in instance_colours(n)]


def write_png(path: Path, rgb: np.ndarray) -> Path:
    """Write an RGB (H, W, 3) uint8 image as PNG, atomically."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    return atomic_write_bytes(path, data.tobytes())


def put_text(img: np.ndarray, text: str, org: tuple[int, int], scale: float,
             colour: RGB = TEXT) -> None:
    """Caption with a dark outline (readable on any background), in place."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, text, org, font, scale, TEXT_SHADOW, 3, cv2.LINE_AA)
    cv2.putText(img, text, org, font, scale, colour, 1, cv2.LINE_AA)


def scaled_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics of the image resized by ``scale`` (pixel-centre convention: ``u' = s(u + 0.5) - 0.5``)."""
    S = np.array([[scale, 0.0, 0.5 * scale - 0.5], [0.0, scale, 0.5 * scale - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, dtype=np.float64)


def scaled_size(image_size: tuple[int, int], scale: float) -> tuple[int, int]:
    """``(width, height)`` of an image resized by ``scale`` (at least 1 x 1)."""
    return max(1, int(round(image_size[0] * scale))), max(1, int(round(image_size[1] * scale)))


# ----------------------------------------------------------------------------------------------
# Projected boxes
# ----------------------------------------------------------------------------------------------


def box_edge_segments(box: Box3D, K: np.ndarray, near: float = NEAR_PLANE,
                      to_cam: np.ndarray | None = None) -> np.ndarray:
    """Pixel segments ``(M, 2, 2)`` of the box's 12 edges clipped to ``z >= near`` in the camera.

    ``to_cam`` (4x4) maps the box's frame to the camera (None: the box is in the camera frame);
    the corners are moved exactly, so a box drawn into a pitched camera keeps its tilt. Edges
    entirely behind the plane are dropped; an edge crossing it is cut at the plane.
    """
    c = box.corners() if to_cam is None else transform_points(to_cam, box.corners())
    a, b = c[BOX_EDGES[:, 0]], c[BOX_EDGES[:, 1]]
    keep = (a[:, 2] >= near) | (b[:, 2] >= near)
    a, b = a[keep], b[keep]
    dz = b[:, 2] - a[:, 2]
    safe = np.where(dz == 0.0, 1.0, dz)
    ta = np.where(a[:, 2] < near, (near - a[:, 2]) / safe, 0.0)
    tb = np.where(b[:, 2] < near, (b[:, 2] - near) / safe, 0.0)
    a2 = a + ta[:, None] * (b - a)
    b2 = b - tb[:, None] * (b - a)
    return np.stack([project(K, a2), project(K, b2)], axis=1).reshape(-1, 2, 2)


#: Pixel coordinates are clamped to this magnitude before integer conversion (OpenCV ints).
MAX_PIXEL = 1e7


def draw_segments(img: np.ndarray, segments: np.ndarray, colour: RGB, thickness: int) -> None:
    """Draw pixel segments onto ``img`` (clipped to the image), in place."""
    h, w = img.shape[:2]
    for p, q in np.clip(segments, -MAX_PIXEL, MAX_PIXEL):
        ok, p1, p2 = cv2.clipLine((0, 0, w, h), tuple(int(round(v)) for v in p),
                                  tuple(int(round(v)) for v in q))
        if ok:
            cv2.line(img, p1, p2, colour, thickness, cv2.LINE_AA)


def draw_projected_boxes(image: np.ndarray, boxes: Sequence[Box3D], K: np.ndarray,
                         colours: Sequence[RGB], captions: Sequence[str],
                         cfg: VisualConfig = VisualConfig(), to_cam: np.ndarray | None = None) -> np.ndarray:
    """A copy of ``image`` (RGB) with every box drawn and captioned; ``to_cam`` (4x4) maps the
    boxes' frame to the camera (None: the boxes are in the camera frame)."""
    img = np.ascontiguousarray(image, dtype=np.uint8).copy()
    h, w = img.shape[:2]
    for box, colour, caption in zip(boxes, colours, captions):
        draw_segments(img, box_edge_segments(box, K, to_cam=to_cam), colour, cfg.edge_thickness)
        b2 = box_to_2d(box, K, world_to_cam=to_cam, image_size=(w, h))
        if b2 is not None and caption:
            x = int(np.clip(b2[0], 0, w - 1))
            y = int(np.clip(b2[1] - 4, 12, h - 1))
            put_text(img, caption, (x, y), cfg.font_scale, colour)
    return img


def contact_sheet(images: Sequence[np.ndarray], columns: int) -> np.ndarray:
    """Equal-size RGB images tiled row by row (black where the last row is short)."""
    if not images:
        raise ValueError("contact sheet of no images")
    h, w = images[0].shape[:2]
    rows = -(-len(images) // columns)
    sheet = np.zeros((rows * h, columns * w, 3), dtype=np.uint8)
    for i, im in enumerate(images):
        r, c = divmod(i, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
    return sheet


def box_captions(boxes: Sequence[Box3D], confidences: np.ndarray) -> list[str]:
    """``"<instance id>: <confidence>"`` per box."""
    return [f"{b.instance_id}: {float(c):.2f}" for b, c in zip(boxes, confidences)]


def source_indices(obs: "Observations") -> np.ndarray:
    """Indices (into ``obs.frames``) of the source frames other than the target."""
    return np.flatnonzero(obs.is_source & (np.arange(obs.num_frames) != 0))


def write_projected_boxes(out_dir: Path, seq: "KittiSequence", obs: "Observations",
                          boxes: Sequence[Box3D], confidences: np.ndarray,
                          cfg: VisualConfig) -> list[Path]:
    """``boxes_target.png`` (full size) and ``boxes_sources.png`` (contact sheet)."""
    colours = box_colours(len(boxes))
    captions = box_captions(boxes, confidences)

    def frame_image(f: int, scale: float) -> np.ndarray:
        image = seq.image(int(obs.frames[f]))
        if scale != 1.0:
            image = cv2.resize(image, scaled_size(obs.image_size, scale), interpolation=cv2.INTER_AREA)
        moved = [b.at_offset(float(obs.dt[f])) for b in boxes]  # exact projection through the pose
        img = draw_projected_boxes(image, moved, scaled_intrinsics(obs.K[f], scale), colours, captions, cfg,
                                   to_cam=np.linalg.inv(obs.cam_to_opt[f]))
        put_text(img, f"frame {int(obs.frames[f])} (dt {int(obs.dt[f]):+d})", (6, 18), cfg.font_scale)
        return img

    files = [write_png(out_dir / "boxes_target.png", frame_image(0, 1.0))]
    sources = source_indices(obs)
    if len(sources):
        sheet = contact_sheet([frame_image(int(f), cfg.sheet_scale) for f in sources], cfg.sheet_columns)
        files.append(write_png(out_dir / "boxes_sources.png", sheet))
    return files


# ----------------------------------------------------------------------------------------------
# Rendered vs real masks
# ----------------------------------------------------------------------------------------------


def render_soft_labels(integrator, K: np.ndarray, cam_to_opt: np.ndarray, dt: float,
                       image_size: tuple[int, int], scale: float) -> np.ndarray:
    """Soft labels ``(N + 1, h, w)`` (instances, then background) of one camera, rendered at
    ``scale`` times the image size through the integrator's ``render_rays`` (no gradients)."""
    w, h = scaled_size(image_size, scale)
    W, H = image_size
    vv, uu = np.mgrid[0:h, 0:w]
    u = (uu.ravel() + 0.5) * (W / w) - 0.5  # small-image pixel centre in full-image pixels
    v = (vv.ravel() + 0.5) * (H / h) - 0.5
    o, d = pixel_rays(K, cam_to_opt, u, v)
    with dr.suspend_grad():
        labels = integrator.render_rays(mi.Point3f(*[to_float(c) for c in o.T]),
                                        mi.Vector3f(*[to_float(c) for c in d.T]),
                                        to_float(np.full(len(u), float(dt))))
        return np.stack([np.array(lab, dtype=np.float32) for lab in labels]).reshape(-1, h, w)


def colourise(layers: np.ndarray, colours: Sequence[RGB]) -> np.ndarray:
    """RGB image ``sum_n layers[n] * colours[n]`` of (N, h, w) weights in [0, 1]."""
    c = np.asarray(colours, dtype=np.float32).reshape(-1, 3)[:len(layers)]
    rgb = np.tensordot(np.clip(layers, 0.0, 1.0), c, axes=(0, 0))
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def soft_iou(a: np.ndarray, b: np.ndarray) -> float:
    """``sum min(a, b) / sum max(a, b)`` of two soft mask stacks (1 when both are empty)."""
    union = float(np.maximum(a, b).sum())
    return float(np.minimum(a, b).sum()) / union if union > 0 else 1.0


def downscaled_masks(masks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Boolean masks (N, H, W) as area fractions (N, h, w) at ``size = (w, h)``."""
    return np.stack([cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA)
                     for m in masks]) if len(masks) else np.zeros((0, size[1], size[0]), np.float32)


def write_mask_comparison(out_dir: Path, optimiser: "BoxOptimiser", cfg: VisualConfig,
                          report: VisualReport) -> list[Path]:
    """``masks.png``: per frame, real masks | rendered soft labels; soft IoUs into ``report``."""
    obs, it = optimiser.obs, optimiser.integrator
    colours = box_colours(optimiser.n)
    sources = source_indices(obs)
    if len(sources) > cfg.mask_sources:
        sources = sources[np.unique(np.linspace(0, len(sources) - 1, cfg.mask_sources).round().astype(int))]
    size = scaled_size(obs.image_size, cfg.mask_scale)
    rows = []
    for f in [0, *[int(s) for s in sources]]:
        real = downscaled_masks(obs.masks[f][optimiser.perm], size)  # row n: instance matched to box n
        rendered = render_soft_labels(it, obs.K[f], obs.cam_to_opt[f], float(obs.dt[f]),
                                      obs.image_size, cfg.mask_scale)[:-1]
        iou = soft_iou(rendered, real)
        report.mask_iou[int(obs.frames[f])] = iou
        left, right = colourise(real, colours), colourise(rendered, colours)
        put_text(left, f"frame {int(obs.frames[f])}: masks", (4, 14), 0.4)
        put_text(right, f"rendered (soft IoU {iou:.2f})", (4, 14), 0.4)
        gap = np.full((size[1], 4, 3), 255, np.uint8)
        rows.append(np.concatenate([left, gap, right], axis=1))
        rows.append(np.full((4, rows[-1].shape[1], 3), 255, np.uint8))
    return [write_png(out_dir / "masks.png", np.concatenate(rows[:-1], axis=0))]


# ----------------------------------------------------------------------------------------------
# Bird's-eye view
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BevFrame:
    """Pixel mapping of the bird's-eye view: ``col = (x - x_min) * ppm``, ``row = (z_max - z) * ppm``."""

    x_min: float
    z_max: float
    ppm: float
    width: int
    height: int

    def to_pixels(self, xz: np.ndarray) -> np.ndarray:
        """``(..., 2)`` ground-plane points ``(x, z)`` to pixel ``(col, row)``."""
        xz = np.asarray(xz, dtype=np.float64)
        return np.stack([(xz[..., 0] - self.x_min) * self.ppm, (self.z_max - xz[..., 1]) * self.ppm], -1)


def bev_frame(boxes: Sequence[Box3D], cfg: VisualConfig) -> BevFrame:
    """The region holding the camera and every box (plus margin), within the configured limits."""
    pts = np.concatenate([np.zeros((1, 2))] + [bev_footprint(b) for b in boxes])
    lo = pts.min(0) - cfg.bev_margin
    hi = pts.max(0) + cfg.bev_margin
    x0 = max(lo[0], -cfg.bev_max_lateral)
    x1 = min(hi[0], cfg.bev_max_lateral)
    z0 = max(lo[1], cfg.bev_forward[0])
    z1 = min(hi[1], cfg.bev_forward[1])
    ppm = cfg.bev_px_per_m
    return BevFrame(x0, z1, ppm, int(np.ceil((x1 - x0) * ppm)) + 1, int(np.ceil((z1 - z0) * ppm)) + 1)


def _polyline(img: np.ndarray, pts: np.ndarray, colour: RGB, thickness: int, closed: bool) -> None:
    p = np.clip(np.rint(pts), -MAX_PIXEL, MAX_PIXEL).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(img, [p], closed, colour, thickness, cv2.LINE_8)


def draw_bev(pred: Sequence[Box3D], gt: Sequence[Box3D], colours: Sequence[RGB],
             captions: Sequence[str] = (), cfg: VisualConfig = VisualConfig()) -> np.ndarray:
    """Bird's-eye view (RGB) of boxes in a gravity-aligned frame (x right, z forward).

    Optimised boxes are outlined in ``colours`` (with a tick from the centre to the front face),
    ground-truth boxes in :data:`BEV_GT`, the camera (origin) and a ``bev_grid`` metre grid in
    greys. Lines are not anti-aliased, so every box pixel has exactly its colour.
    """
    frame = bev_frame([*pred, *gt], cfg)
    img = np.empty((frame.height, frame.width, 3), np.uint8)
    img[:] = BEV_BACKGROUND
    g = cfg.bev_grid
    x_max = frame.x_min + (frame.width - 1) / frame.ppm
    z_min = frame.z_max - (frame.height - 1) / frame.ppm
    for x in np.arange(np.ceil(frame.x_min / g) * g, x_max + 1e-9, g):
        _polyline(img, frame.to_pixels(np.array([[x, z_min], [x, frame.z_max]])), BEV_GRID, 1, False)
    for z in np.arange(np.ceil(z_min / g) * g, frame.z_max + 1e-9, g):
        _polyline(img, frame.to_pixels(np.array([[frame.x_min, z], [x_max, z]])), BEV_GRID, 1, False)
    cam = frame.to_pixels(np.array([[-1.0, 2.0], [0.0, 0.0], [1.0, 2.0]]))
    _polyline(img, cam, BEV_CAMERA, 1, True)
    for b in gt:
        _polyline(img, frame.to_pixels(bev_footprint(b)), BEV_GT, 1, True)
    for i, (b, colour) in enumerate(zip(pred, colours)):
        _polyline(img, frame.to_pixels(bev_footprint(b)), colour, cfg.bev_box_thickness, True)
        front = b.centre + 0.5 * b.size[2] * b.heading
        tick = frame.to_pixels(np.array([[b.centre[0], b.centre[2]], [front[0], front[2]]]))
        _polyline(img, tick, colour, 1, False)
        if i < len(captions):
            corner = frame.to_pixels(bev_footprint(b)).min(0)
            put_text(img, captions[i], (int(corner[0]), int(corner[1]) - 3), 0.35, BEV_TEXT)
    return img


def ground_truth_in_opt_frame(seq: "KittiSequence", obs: "Observations") -> list[Box3D]:
    """Ground-truth boxes of the target frame in the optimisation frame (none without box XML)."""
    if not seq.has_boxes:
        return []
    return [b.transformed(obs.cam_to_opt[0]) for b in seq.ground_truth(int(obs.target))]


def write_bev(out_dir: Path, seq: "KittiSequence", obs: "Observations", boxes: Sequence[Box3D],
              confidences: np.ndarray, cfg: VisualConfig) -> list[Path]:
    """``bev.png``."""
    img = draw_bev(boxes, ground_truth_in_opt_frame(seq, obs), box_colours(len(boxes)),
                   box_captions(boxes, confidences), cfg)
    return [write_png(out_dir / "bev.png", img)]


# ----------------------------------------------------------------------------------------------
# Loss curves
# ----------------------------------------------------------------------------------------------


def loss_figure_png(history: dict[str, list[float]], residual_from: int | None,
                    cfg: VisualConfig = VisualConfig()) -> bytes:
    """PNG bytes of the loss history (log scale; zero terms are left out)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=cfg.loss_figsize, dpi=cfg.loss_dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for key in LOSS_SERIES:
        values = np.asarray(history.get(key, []), dtype=np.float64)
        if values.size and np.any(values > 0):
            ax.plot(np.arange(values.size), np.where(values > 0, values, np.nan), label=key, lw=1.2)
    if residual_from is not None:
        ax.axvline(residual_from, color="grey", ls="--", lw=1, label="residual on")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize="small")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def write_loss_plot(out_dir: Path, optimiser: "BoxOptimiser", result: "OptimisationResult",
                    cfg: VisualConfig) -> list[Path]:
    """``loss.png``."""
    c = optimiser.cfg
    residual_from = c.warmup_steps if c.residual and result.steps > c.warmup_steps else None
    png = loss_figure_png(result.loss_history, residual_from, cfg)
    return [atomic_write_bytes(out_dir / "loss.png", png)]


# ----------------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------------


def instance_sdf_grid(field, box: Box3D, n: int, cfg: VisualConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """SDF of instance ``n`` of an :class:`~vsrd_plugins.sdf.InstanceField` on a box-aligned grid
    at time 0: ``(values (X, Y, Z), grid origin (box-local, m), spacing (m))``.

    The grid covers the box plus ``mesh_pad_cells`` cells; the residual (when the field uses it)
    is evaluated at every grid point.
    """
    half = 0.5 * box.size
    spacing = float(2.0 * half.max() / (cfg.mesh_cells - 2 * cfg.mesh_pad_cells))
    pad = cfg.mesh_pad_cells * spacing
    counts = np.ceil(2.0 * (half + pad) / spacing).astype(int) + 1
    origin = -0.5 * (counts - 1) * spacing
    axes = [origin[j] + spacing * np.arange(counts[j]) for j in range(3)]
    local = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    world = box.centre + local @ box.rotation.T
    with dr.suspend_grad():
        dec = field.decode()
        p = mi.Point3f(*[to_float(c) for c in world.T])
        sdf = field.instance_sdfs(dec, p, to_float(np.zeros(len(world))), field.residual_weights(),
                                  reach=float(pad), instances=[n])[0]
        values = np.array(sdf, dtype=np.float32).reshape(*counts)
    return values, origin, spacing


def instance_mesh(field, box: Box3D, n: int, colour: RGB, cfg: VisualConfig = VisualConfig()):
    """Marching-cubes mesh (``trimesh.Trimesh``, optimisation frame, outward faces) of instance
    ``n``'s zero level set, and the grid spacing. Raises ValueError when the SDF has no surface."""
    import trimesh
    from skimage.measure import marching_cubes

    values, origin, spacing = instance_sdf_grid(field, box, n, cfg)
    if not (values.min() < 0.0 < values.max()):
        raise ValueError(f"instance {box.instance_id}: the SDF has no zero level set on its grid "
                         f"(range {values.min():.3g}..{values.max():.3g} m)")
    verts, faces, _, _ = marching_cubes(values, 0.0, spacing=(spacing,) * 3, gradient_direction="descent")
    world = box.centre + (verts + origin) @ box.rotation.T
    mesh = trimesh.Trimesh(world, faces, vertex_colors=np.tile([*colour, 255], (len(world), 1)),
                           process=False)
    return mesh, spacing


def write_meshes(out_dir: Path, optimiser: "BoxOptimiser", boxes: Sequence[Box3D], cfg: VisualConfig,
                 report: VisualReport) -> list[Path]:
    """``meshes/instance_<id>.ply`` per box (a box without a surface becomes a warning)."""
    files = []
    for n, (box, colour) in enumerate(zip(boxes, box_colours(len(boxes)))):
        try:
            mesh, spacing = instance_mesh(optimiser.integrator.field, box, n, colour, cfg)
        except ValueError as exc:
            report.warnings.append(f"meshes: {exc}")
            continue
        report.mesh_spacing[int(box.instance_id)] = spacing
        files.append(atomic_write_bytes(out_dir / "meshes" / f"instance_{box.instance_id}.ply",
                                        mesh.export(file_type="ply")))
    return files


# ----------------------------------------------------------------------------------------------
# Entry point
# ----------------------------------------------------------------------------------------------


def write_visuals(out_dir: str | Path, seq: "KittiSequence", optimiser: "BoxOptimiser",
                  result: "OptimisationResult", confidences: np.ndarray,
                  cfg: VisualConfig | None = None) -> VisualReport:
    """Write every visual of one optimised target under ``out_dir`` (see module docstring).

    ``optimiser`` is the :class:`~vsrd_mi.optimise.optimiser.BoxOptimiser` after ``run()`` (its
    scene renders the masks and meshes), ``result`` what ``run()`` returned and ``confidences``
    one value per box. Never raises for a failing part: its error is a warning in the report.
    """
    cfg = cfg or VisualConfig()
    out = Path(out_dir)
    obs, boxes = optimiser.obs, result.boxes
    report = VisualReport()
    parts: list[tuple[str, Callable[[], list[Path]]]] = [
        ("boxes", lambda: write_projected_boxes(out, seq, obs, boxes, confidences, cfg)),
        ("masks", lambda: write_mask_comparison(out, optimiser, cfg, report)),
        ("bev", lambda: write_bev(out, seq, obs, boxes, confidences, cfg)),
        ("loss", lambda: write_loss_plot(out, optimiser, result, cfg)),
        ("meshes", lambda: write_meshes(out, optimiser, boxes, cfg, report)),
    ]
    for name, part in parts:
        try:
            report.files.extend(part())
        except Exception as exc:  # a visual must never fail the target (see module docstring)
            message = f"{name}: {type(exc).__name__}: {exc}"
            log.warning("target %s: visual %s", obs.target, message)
            report.warnings.append(message)
    return report
