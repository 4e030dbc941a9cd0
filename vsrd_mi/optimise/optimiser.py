"""Per-target box optimisation (VSRD++ stage 1) through the ``vsrd_silhouette`` Mitsuba scene.

One :class:`BoxOptimiser` holds the Mitsuba scene of a target frame (one sensor per frame, the
integrator with one box per target instance), reads its differentiable parameters through
``mi.traverse`` and optimises them with ``mi.ad.Adam``:

1. every step: sharpness ``s`` and temperature ``tau`` from the cosine schedule (opaque values,
   no recompilation), learning rates decayed exponentially;
2. Hungarian matching of boxes to target-frame mask boxes on ``-DIoU`` (docs/method.md §4);
3. where the silhouette term is on (``weights.silhouette > 0``; off by default): rays drawn per
   frame from the soft masks (:class:`RaySampler`), soft labels rendered by the integrator's
   ray-batch entry point, BCE against the masks;
4. projection loss on every (frame, box) pair where the matched instance is visible; eikonal loss
   while the residual field is on; init regulariser when an initialisation exists (centre and
   velocity as in the paper, plus the size / yaw prior where its weights are set -- the
   ``paper`` preset's long schedule --, :func:`losses.shape_prior_loss`);
5. box-only warm-up: the residual field is neither optimised nor evaluated before
   ``warmup_steps``; no velocity parameters when no instance is dynamic;
6. early stop when the loss and the boxes have converged (:class:`Convergence`).

Where nothing is rendered (``weights.silhouette = 0``, the default) a step is the same small
computation every time: :func:`box_step` runs it from explicit inputs under ``dr.freeze``
(``AutolabelConfig.frozen_step``), which traces and compiles it once and then replays its
kernels (docs/speed.md, "The frozen box step").
"""

from __future__ import annotations

import gc
import time as _time
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.optimize import linear_sum_assignment
from vsrd_plugins.sdf import InstanceField

from ..data.observations import Observations, length_view_px
from ..geometry import boxes2d
from ..geometry.boxes import Box3D
from ..geometry.camera import image_bounds
from ..scene.builder import integrator_dict, scene_dict
from . import hidden_length, losses
from .config import AutolabelConfig, CarProfile, LossWeights
from .parameters import VELOCITY_LATENT, BoxLatents, BoxRanges, CornerRange

INTEGRATOR = "vsrd"
#: Dr.Jit threads while the frozen box step replays. Its kernels are small (a few hundred lanes):
#: on one thread the 440 steps of a target ran 1.3-1.5x faster than on two and bit for bit the
#: same every time, where two threads added the backward pass's reductions in varying orders
#: (docs/speed.md, "Same seed, same labels").
FROZEN_STEP_THREADS = 1
#: Eikonal points are drawn in each box scaled by this factor (the residual's surface lies inside
#: the box; a margin beyond it keeps the field a distance there too).
EIKONAL_SPREAD = 1.2


def latent_values(opts: list) -> dict:
    """The latents the Adam optimisers hold: ``opts[0]``'s box latents (the fitted cuts among
    them) and, when given, ``opts[1]``'s velocities."""
    lat = {k: opts[0][k] for k in opts[0].keys()}
    if len(opts) > 1:
        lat[VELOCITY_LATENT] = opts[1][VELOCITY_LATENT]
    return lat


def decode_latents(opts: list, latents: BoxLatents, fixed: dict):
    """The boxes the Adam optimisers' latents hold: ``(decoded boxes, physical parameters)``.
    ``opts`` as in :func:`latent_values`; ``fixed`` the parameters not optimised (``dynamic``;
    ``velocity`` without a velocity optimiser)."""
    phys = latents.decode(latent_values(opts))
    return InstanceField.decode_parameters({**fixed, **phys}, latents.count), phys


def box_losses(dec, lanes: losses.ProjectionLanes, terms: list, w: LossWeights,
               profile: CarProfile, corner: mi.Float | None = None) -> tuple[mi.Float, mi.Float]:
    """The projection loss of decoded boxes (with their fitted plan-corner cuts ``corner``,
    where given) and the sum of the init terms (anchor, priors, visible surface): every loss term
    that needs no rendering."""
    l_proj = losses.projection_loss(dec, lanes, w.huber_beta, w.projection_huber, w.projection_diou,
                                    containment=w.projection_mode == "containment",
                                    excess=w.projection_excess, profile=profile, corner=corner)
    l_init = mi.Float(0.0)
    for term in terms:
        l_init = l_init + term.loss(dec)
    return l_proj, l_init


def box_step(opts: list, latents: BoxLatents, fixed: dict, lanes: losses.ProjectionLanes,
             target_lanes: losses.ProjectionLanes, terms: list, w: LossWeights, profile: CarProfile):
    """One Adam step of the objective without rendering (:func:`box_losses`), from explicit
    inputs only, so that it runs under ``dr.freeze`` (a frozen function refuses Dr.Jit arrays it
    was not given, and replays its kernels without calling Python).

    Returns, detached: the total, projection and init losses; the centres and sizes (3N each)
    before the step, which the early stop compares; and the target frame's projected boxes
    ``(x1, y1, x2, y2)`` after it, which the next step's matching reads.
    """
    dec, phys = decode_latents(opts, latents, fixed)
    l_proj, l_init = box_losses(dec, lanes, terms, w, profile, phys.get("corner"))
    total = l_proj + l_init
    dr.backward(total)
    for o in opts:
        o.step()
    with dr.suspend_grad():
        after, phys_after = decode_latents(opts, latents, fixed)
        projected = losses.projected_boxes(after, target_lanes, profile, phys_after.get("corner"))[:4]
    return ([dr.detach(x) for x in (total, l_proj, l_init)], [dr.detach(phys["centre"]), dr.detach(phys["size"])],
            [dr.detach(x) for x in projected])


class OptimisationError(RuntimeError):
    """The optimisation of a target produced non-finite values (the target is stopped)."""


def cosine(start: float, end: float, step: int, steps: int) -> float:
    """Cosine interpolation from ``start`` (step 0) to ``end`` (step ``steps``)."""
    x = min(max(step / max(steps, 1), 0.0), 1.0)
    return end + 0.5 * (start - end) * (1.0 + np.cos(np.pi * x))


class RaySampler:
    """Draws pixels per frame with probability proportional to the soft mask weight.

    Sampling is with replacement through the cumulative weights (for ~60 rays out of ~500k pixels
    duplicates are negligible; the reference draws without replacement). Deterministic for a seed.
    """

    def __init__(self, obs: Observations, frames: np.ndarray, rays_per_step: int, seed: int):
        self.obs = obs
        self.frames = frames
        self.per_frame = max(1, rays_per_step // len(frames))
        self.rng = np.random.default_rng(seed)
        w, h = obs.image_size
        self.width = w
        self.cdf = []
        for f in frames:
            wf = obs.weights[f].astype(np.float64).ravel()
            c = np.cumsum(wf)
            self.cdf.append(c / c[-1])
        self.K_inv = [np.linalg.inv(obs.K[f]) for f in frames]

    def sample(self, perm: np.ndarray):
        """Rays and per-box targets: ``(o, d, time, targets)`` with targets[n] for box n."""
        o_all, d_all, t_all, lab_all = [], [], [], []
        for i, f in enumerate(self.frames):
            idx = np.searchsorted(self.cdf[i], self.rng.random(self.per_frame))
            idx = np.minimum(idx, len(self.cdf[i]) - 1)
            v, u = np.divmod(idx, self.width)
            pix = np.stack([u, v, np.ones_like(u)], 0).astype(np.float64)
            d_cam = self.K_inv[i] @ pix
            T = self.obs.cam_to_opt[f]
            d = (T[:3, :3] @ d_cam).T
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            o_all.append(np.repeat(T[None, :3, 3], len(idx), 0))
            d_all.append(d)
            t_all.append(np.full(len(idx), float(self.obs.dt[f])))
            lab_all.append(self.obs.masks[f][:, v, u][perm])  # (N, R): box n <- instance perm[n]
        o = np.concatenate(o_all).astype(np.float32)
        d = np.concatenate(d_all).astype(np.float32)
        labels = np.concatenate(lab_all, axis=1).astype(np.float32)
        return (mi.Point3f(*[losses.to_float(c) for c in o.T]),
                mi.Vector3f(*[losses.to_float(c) for c in d.T]),
                losses.to_float(np.concatenate(t_all)), [losses.to_float(row) for row in labels])


@dataclass
class Convergence:
    """Early-stopping criterion: relative loss improvement and box motion over a window."""

    window: int
    rel_loss: float
    box_tol: float
    losses: list = field(default_factory=list)
    boxes: list = field(default_factory=list)

    def update(self, loss: float, box_vec: np.ndarray) -> bool:
        self.losses.append(loss)
        self.boxes.append(box_vec)
        w = self.window
        if len(self.losses) < 2 * w:
            return False
        recent = float(np.mean(self.losses[-w:]))
        before = float(np.mean(self.losses[-2 * w:-w]))
        improving = (before - recent) > self.rel_loss * abs(before)
        moved = float(np.max(np.abs(self.boxes[-1] - self.boxes[-w])))
        return (not improving) and moved < self.box_tol


@dataclass
class OptimisationResult:
    """Optimised boxes (optimisation frame, target time) and a summary of the run."""

    boxes: list[Box3D]
    instance_ids: np.ndarray  # instance matched to each box
    steps: int
    seconds: float
    loss_history: dict[str, list[float]]
    stopped_early: bool
    sdf_evaluations: int
    projected_lanes: int
    #: (N, 2) per box, its ends (at ``+axis``, at ``-axis``) that the masks held from inside only
    #: and the box's length was extended past (:mod:`.hidden_length`); None when not looked at.
    held_ends: np.ndarray | None = None
    #: (N,) per box, whether no view measured its length (an end free either way) and the length
    #: was set from the prior above the shortest one the masks allow (:mod:`.hidden_length`).
    unmeasured_lengths: np.ndarray | None = None
    #: (N,) per box, whether its length was held by the length prior (a moving box no view
    #: measures the length of, ``LossWeights.length_prior``; all False with the prior off or
    #: without initial boxes); None from code that does not report it.
    length_from_prior: np.ndarray | None = None


class BoxOptimiser:
    """Optimises the boxes of one target frame (see module docstring)."""

    def __init__(self, obs: Observations, boxes: list[Box3D], cfg: AutolabelConfig,
                 init_boxes: list[Box3D] | None = None, surface_points: list | None = None):
        if obs.num_instances == 0:
            raise ValueError(f"target {obs.target}: no instances to optimise")
        for name in ("cam_to_opt", "K"):
            bad = ~np.isfinite(getattr(obs, name)).reshape(obs.num_frames, -1).all(axis=1)
            if bad.any():
                raise ValueError(f"target {obs.target}: non-finite {name} of frame(s) {obs.frames[bad].tolist()}")
        self.obs, self.cfg = obs, cfg
        self.n = obs.num_instances
        self.dynamic = np.array([b.dynamic for b in boxes], dtype=bool) & cfg.velocity
        boxes = [Box3D(b.centre, b.size, b.yaw, b.velocity if d else np.zeros(3), bool(d), b.instance_id)
                 for b, d in zip(boxes, self.dynamic)]
        integ = {**integrator_dict(boxes), "sampling": cfg.sampling, "band_samples": cfg.band_samples,
                 "residual": cfg.residual, "residual_seed": cfg.seed}
        self.scene = mi.load_dict(scene_dict(obs, boxes, integrator=integ))
        self.integrator = self.scene.integrator()
        self.integrator.settings = replace(self.integrator.settings, isolated_rays=cfg.isolated_rays,
                                           residual_gradients=cfg.residual_gradients)
        self.integrator.field.use_residual = False  # the residual field joins after the box-only warm-up
        self.params = mi.traverse(self.scene)
        # the optimiser's own latent variables (parameters.py), decoded into the boxes each step
        self.latents = BoxLatents(BoxRanges(), self.n, CornerRange.of_profile(cfg.car_profile))
        self.start = self.latents.initial(np.stack([b.centre for b in boxes]), np.stack([b.size for b in boxes]),
                                          np.array([b.yaw for b in boxes]), np.stack([b.velocity for b in boxes]))
        if init_boxes is not None and len(init_boxes) != self.n:
            raise ValueError(f"target {obs.target}: init_boxes has {len(init_boxes)} boxes for {self.n} instances")
        self.init_boxes = init_boxes
        #: per box: (points (M, 3), their cameras (M, 3)) of its stereo cloud, or None
        self.surface_points = surface_points
        # supervision frames: target + sources
        self.frames = np.flatnonzero(obs.is_source | (np.arange(obs.num_frames) == 0))
        self.sampler = RaySampler(obs, self.frames, cfg.rays_per_step, cfg.seed)
        #: (N,) the boxes whose length the length prior holds, in place of the width prior
        self.length_from_prior = self._lengths_from_prior()
        self.world_to_cam = np.linalg.inv(obs.cam_to_opt)
        self.bounds = image_bounds(obs.image_size)
        self.perm = np.arange(self.n)
        self._lanes = None
        #: every box in the target frame: the matching projects these
        self.target_lanes = losses.ProjectionLanes(
            np.arange(self.n), np.zeros(self.n), np.repeat(self.world_to_cam[None, 0], self.n, 0),
            np.zeros((self.n, 4)), obs.K[0], self.bounds)
        #: recordings of the frozen step in the last run (0: the step was not frozen)
        self.recordings = 0
        # fresh eikonal points every step: a fixed set left the field free between its points
        self.eik_rng = np.random.default_rng(cfg.seed + 1)
        self.rdf_keys = [k for k in self.params.keys() if k.startswith(f"{INTEGRATOR}.rdf_")]

    def eikonal_points(self) -> np.ndarray:
        """``(N, eikonal_points, 3)`` box-local points of this step's eikonal term, uniform in each
        box enlarged by :data:`EIKONAL_SPREAD` (in units of its half-extents)."""
        return self.eik_rng.uniform(-EIKONAL_SPREAD, EIKONAL_SPREAD, size=(self.n, self.cfg.eikonal_points, 3))

    # -- supervision ---------------------------------------------------------------------------
    def _projection_lanes(self) -> losses.ProjectionLanes:
        obs = self.obs
        box, dt, w2c, tgt, sides = [], [], [], [], []
        for f in self.frames:
            for n in range(self.n):
                inst = self.perm[n]
                if obs.visible[f, inst]:
                    box.append(n)
                    dt.append(obs.dt[f])
                    w2c.append(self.world_to_cam[f])
                    tgt.append(obs.boxes2d[f, inst])
                    sides.append(obs.open_sides[f, inst] if self.cfg.occlusion_aware else np.zeros(4, bool))
        return losses.ProjectionLanes(np.array(box), np.array(dt), np.array(w2c).reshape(-1, 4, 4),
                                      np.array(tgt).reshape(-1, 4), obs.K[0], self.bounds,
                                      np.array(sides, bool).reshape(-1, 4))

    def _match(self, dec, corner: mi.Float | None = None) -> np.ndarray:
        """Hungarian matching of boxes to target-frame instances on -DIoU (``corner``: the
        boxes' fitted cuts, where fitted)."""
        with dr.suspend_grad():
            projected = losses.projected_boxes(dec, self.target_lanes, self.cfg.car_profile, corner)[:4]
        return self._match_projected(np.stack([np.array(v) for v in projected], 1))

    def _match_projected(self, pred: np.ndarray) -> np.ndarray:
        """:meth:`_match` of the boxes' projections ``pred`` (N, 4) into the target frame."""
        masks = self.obs.boxes2d[0]
        cost = -boxes2d.diou_matrix(pred, np.nan_to_num(masks, nan=-1e4))
        cost[:, ~np.all(np.isfinite(masks), axis=1)] = 1e3
        rows, cols = linear_sum_assignment(cost)
        perm = np.arange(self.n)
        perm[rows] = cols
        return perm

    # -- the loop ------------------------------------------------------------------------------
    def _adam(self, params: dict[str, mi.Float], lr: float) -> mi.ad.Adam:
        return mi.ad.Adam(lr=lr, params=params)

    def _write_boxes(self, opt_box: mi.ad.Adam, opt_vel: mi.ad.Adam | None) -> mi.Float | None:
        """Decode the latents held by the Adam optimisers into the integrator's box parameters
        (with their AD graph: the gradients reach the latents). Returns the fitted plan-corner
        cuts (not an integrator parameter), None where not fitted."""
        opts = [opt_box] if opt_vel is None else [opt_box, opt_vel]
        phys = self.latents.decode(latent_values(opts))
        corner = phys.pop("corner", None)
        for key, value in phys.items():
            self.params[f"{INTEGRATOR}.{key}"] = value
        self.params.update()
        return corner

    def run(self, progress=None) -> OptimisationResult:
        cfg = self.cfg
        t0 = _time.time()
        opt_box = self._adam({k: self.start[k] for k in self.latents.box_keys}, cfg.lr.box)
        opt_vel = self._adam({VELOCITY_LATENT: self.start[VELOCITY_LATENT]}, cfg.lr.velocity) if self.dynamic.any() else None
        self._opt_rdf = None  # the residual field's optimisers, once it joins
        w = cfg.weights
        init_terms = self._init_terms(opt_vel is not None)
        history = {k: [] for k in ("total", "projection", "silhouette", "eikonal", "init")}
        conv = Convergence(cfg.early_stop.window, cfg.early_stop.rel_loss, cfg.early_stop.box_tol)
        sdf_evals = 0
        stopped = False
        step = 0
        # the silhouettes are rendered only when their loss counts (the residual field needs them)
        render = w.silhouette > 0
        frozen = None
        if cfg.frozen_step and not render:
            # re-recorded when the lane count changes: widths enter the kernels as constants
            frozen = dr.freeze(box_step, state_fn=lambda opts, latents, fixed, lanes, *rest: (lanes.count,))
            fixed = {k: mi.Float(dr.detach(self.params[f"{INTEGRATOR}.{k}"])) for k in ("dynamic", "velocity")}
        projected_next = None
        threads, collecting = dr.thread_count(), gc.isenabled()
        if frozen is not None:
            # no Dr.Jit memory may be released while the step records (a release deferred until
            # pending kernels finish cannot be recorded, and Dr.Jit aborts): collect Python's
            # garbage and finish pending work now, and keep the collector off until the loop ends
            gc.collect()
            dr.sync_thread()
            gc.disable()
            dr.set_thread_count(FROZEN_STEP_THREADS)
        try:
            for step in range(cfg.steps):
                decay = cfg.lr.decay ** (step / max(cfg.steps, 1))
                if frozen is not None:
                    vals, box_vec, projected_next = self._frozen_step(frozen, decay, opt_box, opt_vel, fixed,
                                                                      init_terms, projected_next)
                else:
                    vals, sdf = self._step(step, decay, opt_box, opt_vel, init_terms, render)
                    sdf_evals += sdf
                    box_vec = None
                if not np.all(np.isfinite(vals)):
                    raise OptimisationError(f"target {self.obs.target}: non-finite loss at step {step}: {vals}")
                for k, v in zip(history, vals):
                    history[k].append(v)
                if progress is not None:
                    progress(step, vals[0])
                if cfg.early_stop.enabled and step >= cfg.early_stop.min_fraction * cfg.steps:
                    if conv.update(vals[0], self._box_vector() if box_vec is None else box_vec):
                        stopped = True
                        break
        finally:
            dr.set_thread_count(threads)
            if collecting:
                gc.enable()
        self.recordings = frozen.n_recordings if frozen is not None else 0
        corner = self._write_boxes(opt_box, opt_vel)
        for o in self._opt_rdf.values() if self._opt_rdf else ():
            self.params.update(o)
        boxes, held, unmeasured = self.boxes(), None, None
        if cfg.hidden_length.enabled and cfg.occlusion_aware and w.projection_mode == "symmetric":
            lengths = hidden_length.estimate_hidden_lengths(boxes, self._box_projection_loss(corner),
                                                            cfg.hidden_length)
            boxes, held, unmeasured = lengths.boxes, lengths.held, lengths.unmeasured
        return OptimisationResult(boxes=boxes, instance_ids=self.obs.instance_ids[self.perm],
                                  steps=step + 1, seconds=_time.time() - t0, loss_history=history,
                                  stopped_early=stopped, sdf_evaluations=sdf_evals,
                                  projected_lanes=self._lanes.count if self._lanes else 0, held_ends=held,
                                  unmeasured_lengths=unmeasured, length_from_prior=self.length_from_prior)

    def _box_projection_loss(self, corner: mi.Float | None) -> hidden_length.LaneLoss:
        """The projection loss on every lane of every frame (the lanes of the last matching), as a
        function of the boxes' centres, sizes and yaws (velocities and dynamic flags as optimised;
        ``corner`` the fitted cuts)."""
        b = self.integrator.boxes()
        lanes = self._lanes if self._lanes is not None else self._projection_lanes()
        return hidden_length.projection_box_loss(lanes, self.n, self.cfg.weights,
                                                 self.cfg.car_profile, corner, b["velocity"], b["dynamic"])

    def _init_terms(self, velocity: bool) -> list:
        """The terms logged together as "init": the anchor (with the velocities where
        ``velocity``), the priors on size, yaw, width and length (the length prior on the
        boxes of :attr:`length_from_prior`, which take no width prior) and the visible surface
        (those whose weights are set)."""
        w = self.cfg.weights
        anchor = prior = None
        init_weights = np.where(self.dynamic, w.init_dynamic, w.init)
        if self.init_boxes is not None:
            sizes, yaws = np.stack([b.size for b in self.init_boxes]), np.array([b.yaw for b in self.init_boxes])
            if np.any(init_weights > 0):
                normals = None
                faces = np.where(self.dynamic, w.init_anchor_dynamic == "seen_faces", w.init_anchor == "seen_faces")
                if faces.any():  # zero normals keep a box's centre anchor
                    normals = losses.seen_face_normals(self.init_boxes)
                    normals[~faces] = 0.0
                anchor = losses.InitAnchor(np.stack([b.centre for b in self.init_boxes]),
                                           np.stack([b.velocity for b in self.init_boxes])
                                           if velocity else None, self.dynamic, init_weights,
                                           face_normals=normals, init_half=0.5 * sizes,
                                           side_inset=self.cfg.car_profile.mirror)
            prior = losses.ShapePrior(sizes, yaws,
                                      np.where(self.dynamic, w.init_size_dynamic, w.init_size),
                                      np.where(self.dynamic, w.init_yaw_dynamic, w.init_yaw))
            if not prior.active:
                prior = None
        end_on = self.length_from_prior
        width_prior = losses.WidthPrior(np.where(end_on, 0.0, w.width_prior)) if w.width_prior > 0 else None
        length_prior = (losses.LengthPrior(np.where(end_on, w.length_prior, 0.0), mirror=self.cfg.car_profile.mirror)
                        if end_on.any() else None)
        surface = self._visible_surface()
        return [t for t in (anchor, prior, width_prior, length_prior, surface) if t is not None]

    def _lengths_from_prior(self) -> np.ndarray:
        """(N,) the moving boxes whose length the length prior holds: in no view of the target or
        its sources does their initial box's 2D box move by ``weights.length_prior_px`` when its
        far end moves out (:func:`~vsrd_mi.data.observations.length_view_px`); none without
        initial boxes or with the prior off."""
        w = self.cfg.weights
        end_on = np.zeros(self.n, dtype=bool)
        if w.length_prior <= 0 or self.init_boxes is None:
            return end_on
        for i in np.flatnonzero(self.dynamic):
            end_on[i] = length_view_px(self.init_boxes[i], self.obs, self.frames) < w.length_prior_px
        return end_on

    def _update_lanes(self, perm: np.ndarray) -> None:
        """The projection lanes of the matching ``perm`` (rebuilt only when it changed)."""
        if self._lanes is None or not np.array_equal(perm, self.perm):
            self.perm = perm
            self._lanes = self._projection_lanes()

    def _frozen_step(self, frozen, decay: float, opt_box: mi.ad.Adam, opt_vel: mi.ad.Adam | None, fixed: dict,
                     init_terms: list, projected: np.ndarray | None) -> tuple[list[float], np.ndarray, np.ndarray]:
        """One step through the frozen :func:`box_step`: learning rates, the matching of the boxes
        the previous step left (``projected``: their target-frame projection; None at the first
        step), the step. Returns the logged losses, the box vector the early stop compares and
        this step's projection for the next."""
        cfg = self.cfg
        # one fresh opaque rate per parameter: a shared array is scaled in place by Adam once per
        # parameter, and a Python float would enter the recording as a constant
        opt_box.set_learning_rate({k: dr.opaque(mi.Float, cfg.lr.box * decay) for k in self.latents.box_keys})
        if opt_vel is not None:
            opt_vel.set_learning_rate({VELOCITY_LATENT: dr.opaque(mi.Float, cfg.lr.velocity * decay)})
        if projected is None:  # the first step's boxes are matched as unfrozen
            corner = self._write_boxes(opt_box, opt_vel)
            perm = self._match(self.integrator.field.decode(), corner)
        else:
            perm = self._match_projected(projected)
        self._update_lanes(perm)
        opts = [o for o in (opt_box, opt_vel) if o is not None]
        (total, l_proj, l_init), (centre, size), after = frozen(
            opts, self.latents, fixed, self._lanes, self.target_lanes, init_terms, cfg.weights, cfg.car_profile)
        vals = [float(total[0]), float(l_proj[0]), 0.0, 0.0, float(l_init[0])]
        return (vals, np.concatenate([np.array(centre), np.array(size)]),
                np.stack([np.array(v) for v in after], 1))

    def _step(self, step: int, decay: float, opt_box: mi.ad.Adam, opt_vel: mi.ad.Adam | None,
              init_terms: list, render: bool) -> tuple[list[float], int]:
        """One traced step: schedule, matching, the silhouettes where ``render``, the residual
        field after its warm-up, every loss, backward and Adam. Returns the logged losses
        (total, projection, silhouette, eikonal, init) and the SDF evaluations of the render."""
        cfg, it, w = self.cfg, self.integrator, self.cfg.weights
        s_inv = cosine(cfg.schedule.inv_sharpness_start, cfg.schedule.inv_sharpness_end, step, cfg.steps)
        tau = cosine(cfg.schedule.tau_start, cfg.schedule.tau_end, step, cfg.steps)
        it.set_schedule(1.0 / s_inv, tau)
        opt_box.set_learning_rate(cfg.lr.box * decay)
        if opt_vel is not None:
            opt_vel.set_learning_rate(cfg.lr.velocity * decay)
        residual_on = cfg.residual and step >= cfg.warmup_steps
        if residual_on and self._opt_rdf is None:
            it.field.use_residual = True
            self._opt_rdf = {"emb": self._adam({f"{INTEGRATOR}.rdf_embedding": self.params[f"{INTEGRATOR}.rdf_embedding"]},
                                               cfg.lr.embedding),
                             "hyper": self._adam({k: self.params[k] for k in self.rdf_keys if "hyper" in k},
                                                 cfg.lr.hypernetwork)}
        rdf = list(self._opt_rdf.values()) if self._opt_rdf else []
        if rdf:
            rdf[0].set_learning_rate(cfg.lr.embedding * decay)
            rdf[1].set_learning_rate(cfg.lr.hypernetwork * decay)
        corner = self._write_boxes(opt_box, opt_vel)
        for o in rdf:
            self.params.update(o)
        dec = it.field.decode()
        self._update_lanes(self._match(dec, corner))
        l_proj, l_init = box_losses(dec, self._lanes, init_terms, w, cfg.car_profile, corner)
        total = l_proj + l_init
        l_sil = l_eik = mi.Float(0.0)
        sdf_evals = 0
        if render:
            o, d, t, targets = self.sampler.sample(self.perm)
            labels = it.render_rays(o, d, t)[:-1]
            sdf_evals = it.last_stats.get("sdf_evals", 0)
            l_sil = losses.silhouette_loss(labels, targets, w.bce_eps)
            total = total + w.silhouette * l_sil
        if residual_on and w.eikonal > 0:
            l_eik = losses.eikonal_loss(it.field, dec, it.field.residual_weights(), self.eikonal_points(),
                                        cfg.eikonal_step)
            total = total + w.eikonal * l_eik
        dr.backward(total)
        for o in [o for o in (opt_box, opt_vel) if o is not None] + rdf:
            o.step()
        return [float(x[0]) for x in (total, l_proj, l_sil, l_eik, l_init)], sdf_evals

    def _visible_surface(self) -> losses.VisibleSurface | None:
        """The visible-surface term of the boxes that have points and a weight (None when off):
        ``weights.surface`` for parked boxes, ``weights.surface_dynamic`` for moving ones, whose
        points the initialisation moved to the target time."""
        w, sc = self.cfg.weights, self.cfg.surface
        weights = np.where(self.dynamic, w.surface_dynamic, w.surface)
        if not np.any(weights > 0) or self.surface_points is None:
            return None
        points = [sp if sp is not None else (None, None) for sp in self.surface_points]
        term = losses.VisibleSurface([p for p, _ in points], [c for _, c in points], weights,
                                     sc.scale, sc.reference_range, sc.max_points,
                                     sc.quantile,
                                     seed=self.cfg.seed, by_range=sc.quantile_by_range,
                                     min_quantile=sc.min_quantile)
        return term if term.active else None

    def _box_vector(self) -> np.ndarray:
        b = self.integrator.boxes()
        return np.concatenate([b["centre"].ravel(), b["size"].ravel()])

    def boxes(self) -> list[Box3D]:
        """Current boxes (optimisation frame, target time), box n labelled with instance perm[n]."""
        b = self.integrator.boxes()
        if not (np.all(np.isfinite(b["centre"])) and np.all(np.isfinite(b["size"]))
                and np.all(np.isfinite(b["velocity"]))):
            raise OptimisationError(f"target {self.obs.target}: non-finite box parameters")
        out = []
        for n in range(self.n):
            dyn = bool(self.dynamic[n])
            out.append(Box3D(b["centre"][n], b["size"][n], b["yaw"][n],
                             b["velocity"][n] if dyn else np.zeros(3), dyn,
                             int(self.obs.instance_ids[self.perm[n]])))
        return out
