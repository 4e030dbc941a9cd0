"""vsrd-mi evaluate stage: pseudo labels against KITTI-360 ground truth (REFERENCE §9).

* :mod:`.matching` - the KITTI devkit's per-frame matching (TP / FP / FN, ignored boxes);
* :mod:`.ap` - AP|R40 and AP|R11 on the exact precision curve and on the devkit's 41 thresholds;
* :mod:`.metrics` - Hungarian-matched pairs: mean IoUs, centre / yaw / size errors, static / dynamic;
* :mod:`.sequence` - :func:`evaluate_frames` (in-memory boxes) and :func:`evaluate_sequence`
  (label files + a KITTI-360 sequence);
* :mod:`.cli` - the ``vsrd-mi eval`` sub-command.
"""

from .sequence import EvalConfig, FrameBoxes, evaluate_frames, evaluate_sequence

__all__ = ["EvalConfig", "FrameBoxes", "evaluate_frames", "evaluate_sequence"]
