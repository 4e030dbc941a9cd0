"""vsrd-mi evaluate stage: pseudo labels against KITTI-360 ground truth (``docs/evaluation.md``).

* :mod:`.matching` - the KITTI devkit's per-frame matching (TP / FP / FN, ignored boxes, the
  orientation similarity of AOS);
* :mod:`.ap` - AP|R40 / AP|R11 and AOS on the exact precision curve and on the devkit's 41 thresholds;
* :mod:`.metrics` - Hungarian-matched pairs: mean IoUs, centre / yaw / size errors, heading
  accuracy, signed size bias, the share of cars without a box, static / dynamic and breakdowns;
* :mod:`.attributes` - the optional per-car attributes sidecar (class, parking, occlusion);
* :mod:`.sequence` - :func:`evaluate_frames` (in-memory boxes) and :func:`evaluate_sequence`
  (label files + a KITTI-360 sequence), with the mask (default) or projection protocol;
* :mod:`.cli` - the ``vsrd-mi eval`` sub-command.
"""

from .attributes import CarAttributes, read_attributes
from .metrics import BreakdownBins, GroundTruthRecord, heading_accuracy, size_bias, summarise
from .sequence import (GT_BOXES_MASK, GT_BOXES_PROJECTED, EvalConfig, FrameBoxes, evaluate_frames,
                       evaluate_sequence)

__all__ = ["BreakdownBins", "CarAttributes", "EvalConfig", "FrameBoxes", "GT_BOXES_MASK", "GT_BOXES_PROJECTED",
           "GroundTruthRecord", "evaluate_frames", "evaluate_sequence", "heading_accuracy", "read_attributes",
           "size_bias", "summarise"]
