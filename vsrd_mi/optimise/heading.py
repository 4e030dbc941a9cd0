"""Which way a parked car faces: the evidence of its lamps and silhouettes, front against back.

The box optimisation fixes a parked car's axis but not its front: a box turned end for end
renders the same silhouette and projects to the same 2D boxes. A car's silhouette is not
symmetric, though (bonnet and tail, the cabin's place: :mod:`vsrd_mi.geometry.silhouettes`), and
a sequence sees it from many angles. For each parked box this module rasterises generic body
templates fitted to the box, once facing its yaw and once turned by 180 degrees, into every frame
where the instance is seen, and compares them with the instance's masks:

* per frame, the IoU of template and mask over the pixels that can tell (the other target
  instances' masks are left out: a car in front hides what is behind it);
* per heading, the best template's mean IoU over the frames (:func:`heading_scores`);
* the evidence is the difference of the two (positive: the box faces its yaw), and the box is
  turned when the evidence for the other end exceeds ``HeadingConfig.min_evidence``.

A second cue is colour: rear lamps are red, front lamps white or amber. Frame by frame, an end of
the box (its rear or front fifth) looks lamped when a lamp's share of its visible pixels is red
(:func:`lamp_evidence`); where the lamped ends agree on which is the rear, the lamps decide, before
the silhouettes (a red car's paint covers most of both ends and leaves it to them). Where no end
looks lamped, a rear lamp seen from the side or from afar still shows a few red pixels, and a front
none: of two ends both seen, the one whose pixels are clearly more often lamp red over all frames
is the rear (:func:`red_balance`, also before the silhouettes). The same
reading says more: every car's rear carries red lamps, so an end seen nearly head-on, large enough
to show them, and without any red is its front (:func:`bare_end_evidence`: a car seen only from
the front). Bare ends are the weakest cue (a rear too far or too dark to show red, or a box whose
axis is wrong, votes wrongly; on the development set about three votes in four were right) and
decide only where the silhouettes cannot.

Where the evidence is weaker than that (a car seen end-on only, or too small), an optional,
documented prior decides (``HeadingConfig.prior``: which way parked cars usually face on each side
of a right- or left-hand traffic street); the default has none and keeps the optimiser's yaw.
Moving cars are left alone: their velocity says where their front is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.observations import Observations
from ..data.png import read_png
from ..geometry.boxes import Box3D, wrap_angle
from ..geometry.camera import box_to_2d
from ..geometry.silhouettes import BODY_TEMPLATES, BodyPart, BodyTemplate, rasterise_template
from .config import HeadingConfig

#: Pixels added around a view's region of interest (mask box and projected box).
ROI_MARGIN_PX = 3
#: The box's front and rear fifths (full height and width), where lamps sit.
FRONT_END = BodyTemplate("front", (BodyPart(((0.6, 0.0), (1.0, 0.0), (1.0, 1.0), (0.6, 1.0)), 1.0, 1.0),))
REAR_END = BodyTemplate("rear", (BodyPart(((-1.0, 0.0), (-0.6, 0.0), (-0.6, 1.0), (-1.0, 1.0)), 1.0, 1.0),))
#: A pixel is lamp red when its red channel exceeds this and both others times this ratio: rear
#: lamps are saturated red, amber indicators (green about 60 % of red) and paint in shadow are not.
RED_MIN = 60
RED_RATIO = 2.2
#: An end of a car looks lamped when this share of its visible pixels is lamp red: a pair of rear
#: lamps covers a few to a quarter of a car's end; red paint covers most of it.
LAMP_SHARE = (0.01, 0.3)
#: Red balance: over all frames, the end with at least this many lamp-red pixels (a lamp seen edge-on
#: or far: a few pixels) ...
MIN_RED_PIXELS = 3
#: ... and a red share at least this many times the other end's is the rear (evidence 1/3 or more).
RED_DOMINANCE = 2.0
#: An end takes part in a frame when at least this many of its pixels are visible.
MIN_END_PIXELS = 30
#: An end counts as bare (no lamp red) only when it faces the camera within 60 degrees of head-on
#: (the cosine between its outward normal and the direction to the camera is at least this) ...
BARE_FACING_COS = 0.5
#: ... and shows at least this many pixels: a lamp pair's smallest share (LAMP_SHARE[0]) is then
#: three pixels or more.
MIN_BARE_END_PIXELS = 300


@dataclass(frozen=True)
class HeadingDecision:
    """Outcome for one box: the box to keep, and why."""

    box: Box3D
    #: Evidence for the box's own heading over the opposite one (before any turn): the vote share of
    #: the lamps or bare ends, the red balance, or the silhouettes' mean-IoU advantage.
    evidence: float
    #: Frames that took part.
    views: int
    #: ``"lamps"``, ``"red balance"``, ``"silhouette"``, ``"bare ends"``, ``"prior"``, ``"kept"``
    #: (no evidence, no prior) or ``"moving"``.
    source: str
    #: Whether the box was turned by 180 degrees.
    turned: bool

    def to_dict(self) -> dict:
        """JSON record; ``evidence`` is for the kept box's own front (positive: the silhouettes agree)."""
        return {"evidence": float(-self.evidence if self.turned else self.evidence), "views": int(self.views),
                "source": self.source, "turned": bool(self.turned)}


def turned(box: Box3D) -> Box3D:
    """The same box facing the other way."""
    return Box3D(box.centre, box.size, float(wrap_angle(box.yaw + np.pi)), box.velocity, box.dynamic,
                 box.instance_id)


def _roi(mask_box: np.ndarray, proj: np.ndarray | None, image_size: tuple[int, int]) -> tuple[int, int, int, int]:
    boxes = [mask_box] + ([proj] if proj is not None else [])
    lo = np.min([b[:2] for b in boxes], axis=0) - ROI_MARGIN_PX
    hi = np.max([b[2:] for b in boxes], axis=0) + ROI_MARGIN_PX
    w, h = image_size
    x0, y0 = (int(max(np.floor(v), 0)) for v in lo)
    x1, y1 = int(min(np.ceil(hi[0]) + 1, w)), int(min(np.ceil(hi[1]) + 1, h))
    return x0, y0, x1, y1


def _iou(a: np.ndarray, b: np.ndarray, care: np.ndarray) -> float:
    union = np.count_nonzero((a | b) & care)
    return float(np.count_nonzero(a & b & care)) / union if union else 0.0


def _view_scores(templates: tuple[BodyTemplate, ...], boxes: tuple[Box3D, Box3D], w2c: np.ndarray,
                 K: np.ndarray, roi: tuple[int, int, int, int], mask: np.ndarray,
                 care: np.ndarray) -> np.ndarray | None:
    """``(templates, 2)`` IoUs of each template facing either way in one frame (None when a
    template reaches behind the camera there)."""
    row = np.zeros((len(templates), 2))
    for k, template in enumerate(templates):
        for side, b in enumerate(boxes):
            sil = rasterise_template(template, b, w2c, K, roi)
            if sil is None:
                return None
            row[k, side] = _iou(sil, mask, care)
    return row


def heading_scores(box: Box3D, n: int, obs: Observations,
                   templates: tuple[BodyTemplate, ...] = BODY_TEMPLATES,
                   min_mask_pixels: int = HeadingConfig.min_mask_pixels) -> tuple[float, float, int]:
    """``(score facing box.yaw, score facing the other way, frames used)`` of box ``n`` (matched
    to instance ``n`` of ``obs``): per heading the best template's mean silhouette IoU
    over the frames where the instance's mask has at least ``min_mask_pixels`` pixels."""
    back = turned(box)
    per_template = 0.0
    views = 0
    for f in range(obs.num_frames):
        mask_full = obs.masks[f, n]
        if np.count_nonzero(mask_full) < min_mask_pixels:
            continue
        w2c = np.linalg.inv(obs.cam_to_opt[f])
        moved, moved_back = box.at_offset(float(obs.dt[f])), back.at_offset(float(obs.dt[f]))
        proj = box_to_2d(moved, obs.K[f], world_to_cam=w2c, image_size=obs.image_size)
        x0, y0, x1, y1 = roi = _roi(obs.boxes2d[f, n], proj, obs.image_size)
        mask = mask_full[y0:y1, x0:x1]
        others = np.delete(obs.masks[f], n, axis=0)[:, y0:y1, x0:x1].any(axis=0)
        care = ~(others & ~mask)
        row = _view_scores(templates, (moved, moved_back), w2c, obs.K[f], roi, mask, care)
        if row is not None:
            per_template += row
            views += 1
    if views == 0:
        return 0.0, 0.0, 0
    mean = per_template / views
    return float(mean[:, 0].max()), float(mean[:, 1].max()), views


def prior_faces_yaw(box: Box3D, prior: str) -> bool | None:
    """Whether the traffic-side prior says ``box`` faces its own yaw (None for no prior)."""
    if prior == "none":
        return None
    along_ego = box.heading[2] >= 0.0               # optimisation frame: the ego looks along +z
    on_right = box.centre[0] >= 0.0
    with_traffic = on_right if prior == "right-hand" else not on_right
    return along_ego == with_traffic


def lamp_red(image: np.ndarray) -> np.ndarray:
    """Pixels of an RGB image that look like a lit or unlit rear lamp (see :data:`RED_RATIO`)."""
    r, g, b = (image[..., k].astype(np.int32) for k in range(3))
    return (r > RED_MIN) & (r > RED_RATIO * g) & (r > RED_RATIO * b)


#: One end of a box in one frame: ``(end (0 rear, 1 front), pixels, red share, facing cosine)``.
Reading = tuple[int, int, float, float]


def end_readings(box: Box3D, n: int, obs: Observations, images: list[np.ndarray | None],
                 min_mask_pixels: int = HeadingConfig.min_mask_pixels) -> list[Reading]:
    """Per frame whose image is given and whose mask has at least ``min_mask_pixels`` pixels, per
    end of the box (0: its rear, 1: its front fifth, for ``box.yaw``) that shows at least
    :data:`MIN_END_PIXELS` mask pixels of its own: ``(end, pixels, red share, facing)``, where
    ``facing`` is the cosine between the end's outward normal and the direction to the camera."""
    readings = []
    for f in range(obs.num_frames):
        mask_full = obs.masks[f, n]
        if images[f] is None or np.count_nonzero(mask_full) < min_mask_pixels:
            continue
        w2c = np.linalg.inv(obs.cam_to_opt[f])
        moved = box.at_offset(float(obs.dt[f]))
        proj = box_to_2d(moved, obs.K[f], world_to_cam=w2c, image_size=obs.image_size)
        x0, y0, x1, y1 = roi = _roi(obs.boxes2d[f, n], proj, obs.image_size)
        mask = mask_full[y0:y1, x0:x1]
        red = lamp_red(images[f][y0:y1, x0:x1]) & mask
        ends = [rasterise_template(t, moved, w2c, obs.K[f], roi) for t in (REAR_END, FRONT_END)]
        if ends[0] is None or ends[1] is None:
            continue
        camera = obs.cam_to_opt[f][:3, 3]
        forward = np.asarray(moved.heading, dtype=float)
        for k, (own, other) in enumerate(((ends[0], ends[1]), (ends[1], ends[0]))):
            region = mask & own & ~other
            pixels = np.count_nonzero(region)
            if pixels < MIN_END_PIXELS:
                continue
            normal = forward if k == 1 else -forward
            to_camera = camera - (np.asarray(moved.centre) + normal * moved.size[2] / 2)
            facing = float(normal @ to_camera / max(np.linalg.norm(to_camera), 1e-9))
            readings.append((k, pixels, np.count_nonzero(red & region) / pixels, facing))
    return readings


def _votes(rear: int, front: int) -> tuple[float, int]:
    total = rear + front
    return ((rear - front) / total if total else 0.0), int(total)


def lamp_votes(readings: list[Reading]) -> tuple[float, int]:
    """``(evidence, views)`` of lamped ends among :func:`end_readings`' readings (see :func:`lamp_evidence`)."""
    lamped = [k for k, _, share, _ in readings if LAMP_SHARE[0] <= share <= LAMP_SHARE[1]]
    return _votes(lamped.count(0), lamped.count(1))


def red_balance(readings: list[Reading]) -> tuple[float, int]:
    """``(evidence, views)`` of the lamp red each end shows over :func:`end_readings`' readings
    (ends redder than :data:`LAMP_SHARE` allows, i.e. red paint, left out). Per end the red share
    of all its visible pixels is pooled over the frames: with shares ``r`` at the rear and ``f`` at
    the front, ``(r - f) / (r + f)`` when both ends were seen, the redder one shows at least
    :data:`MIN_RED_PIXELS` red pixels and its share is at least :data:`RED_DOMINANCE` times the
    other's, else 0 (positive: the box faces its yaw). Shares, not pixel counts: an end seen
    head-on shows more of everything, stray reddish pixels too, than the far end. ``views`` counts
    the readings with any lamp red."""
    red, pixels = [0.0, 0.0], [0, 0]
    views = 0
    for k, count, share, _ in readings:
        if share <= LAMP_SHARE[1]:
            red[k] += share * count
            pixels[k] += count
            views += share > 0
    if min(pixels) == 0:
        return 0.0, views
    rear, front = red[0] / pixels[0], red[1] / pixels[1]
    redder = 0 if rear >= front else 1
    if red[redder] < MIN_RED_PIXELS or max(rear, front) < RED_DOMINANCE * min(rear, front):
        return 0.0, views
    return (rear - front) / (rear + front), views


def bare_end_votes(readings: list[Reading]) -> tuple[float, int]:
    """``(evidence, views)`` of bare ends among :func:`end_readings`' readings (see :func:`bare_end_evidence`)."""
    bare = [k for k, pixels, share, facing in readings
            if facing >= BARE_FACING_COS and pixels >= MIN_BARE_END_PIXELS and share < LAMP_SHARE[0]]
    return _votes(bare.count(1), bare.count(0))


def lamp_evidence(box: Box3D, n: int, obs: Observations, images: list[np.ndarray | None],
                  min_mask_pixels: int = HeadingConfig.min_mask_pixels) -> tuple[float, int]:
    """``(evidence, views)``: an end read by :func:`end_readings` looks lamped when
    :data:`LAMP_SHARE` of its pixels are lamp red (a lamp's share of an end; red paint covers more
    and is left out). The evidence is the views with a lamped rear minus those with a lamped
    front, over both (positive: the box faces its yaw); ``views`` counts the lamped ends."""
    return lamp_votes(end_readings(box, n, obs, images, min_mask_pixels))


def bare_end_evidence(box: Box3D, n: int, obs: Observations, images: list[np.ndarray | None],
                      min_mask_pixels: int = HeadingConfig.min_mask_pixels) -> tuple[float, int]:
    """``(evidence, views)`` of bare ends: an end read by :func:`end_readings` that faces the camera
    (:data:`BARE_FACING_COS`), shows :data:`MIN_BARE_END_PIXELS` or more and has less than
    :data:`LAMP_SHARE`'s lower bound of lamp red is taken for the front. The evidence is the views
    with a bare front minus those with a bare rear, over both (positive: the box faces its yaw)."""
    return bare_end_votes(end_readings(box, n, obs, images, min_mask_pixels))


def _decided(box: Box3D, evidence: float, views: int, source: str) -> HeadingDecision:
    """The decision of a cue whose signed ``evidence`` is for the box's own front: turned when negative."""
    return HeadingDecision(turned(box) if evidence < 0 else box, float(evidence), views, source, bool(evidence < 0))


def _vote_decision(box: Box3D, votes: tuple[float, int], source: str, cfg: HeadingConfig) -> HeadingDecision | None:
    """The decision of a colour cue's votes, or None when too few views or too weak a majority."""
    evidence, seen = votes
    if seen >= cfg.min_lamp_views and abs(evidence) >= cfg.min_lamp_evidence:
        return _decided(box, evidence, seen, source)
    return None


def decide_heading(box: Box3D, n: int, obs: Observations, cfg: HeadingConfig,
                   images: list[np.ndarray | None] | None = None) -> HeadingDecision:
    """Front / back of one optimised box (``n``: its instance in ``obs``), see the module doc.
    ``images``: the frames' left images (RGB), for the lamps (None: silhouettes only)."""
    if box.dynamic:
        return HeadingDecision(box, 0.0, 0, "moving", False)
    readings = end_readings(box, n, obs, images, cfg.min_mask_pixels) if images else []
    if readings and (decision := _vote_decision(box, lamp_votes(readings), "lamps", cfg)):
        return decision
    if readings and cfg.red_balance:
        evidence, seen = red_balance(readings)
        if evidence != 0.0:
            return _decided(box, evidence, seen, "red balance")
    fwd, bwd, views = heading_scores(box, n, obs, min_mask_pixels=cfg.min_mask_pixels)
    evidence = fwd - bwd
    if abs(evidence) > cfg.min_evidence:
        return _decided(box, evidence, views, "silhouette")
    if readings and cfg.bare_ends and (decision := _vote_decision(box, bare_end_votes(readings), "bare ends", cfg)):
        return decision
    faces = prior_faces_yaw(box, cfg.prior)
    turn, source = (False, "kept") if faces is None else (not faces, "prior")
    return HeadingDecision(turned(box) if turn else box, evidence, views, source, turn)


def frame_images(obs: Observations) -> list[np.ndarray]:
    """The left RGB image of every frame of ``obs``."""
    w, h = obs.image_size
    return [read_png(p, dtype=np.uint8, channels=3, size=(w, h)) for p in obs.image_paths_left]


def decide_headings(boxes: list[Box3D], instance_index: np.ndarray, obs: Observations,
                    cfg: HeadingConfig) -> list[HeadingDecision]:
    """:func:`decide_heading` for every box; ``instance_index[k]`` is box k's instance in ``obs``."""
    if not cfg.enabled:
        return [HeadingDecision(b, 0.0, 0, "kept", False) for b in boxes]
    images = frame_images(obs) if cfg.lamps and any(not b.dynamic for b in boxes) else None
    return [decide_heading(b, int(i), obs, cfg, images) for b, i in zip(boxes, instance_index)]
