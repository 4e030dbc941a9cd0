"""Input of the initialisation stage: posed, rectified stereo frames with instance masks.

This type is deliberately independent of the data layer: anything that can produce rectified
stereo images, masks, intrinsics and a pose can feed :func:`vsrd_mi.init.attributes.initialise`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class StereoFrame:
    """One frame of a sequence as seen by the initialisation.

    Attributes:
        frame_offset: frame index minus the target frame index (velocity is per frame index).
        left: left image, HxWx3 uint8 RGB, rectified.
        right: right image, HxWx3 uint8 RGB, rectified with ``left`` (may be None only when
            ``depth`` is given; the photometric-warp selection is then skipped).
        masks: instance id -> HxW boolean mask in the left image.
        K: 3x3 intrinsics of the rectified left camera.
        baseline: stereo baseline in metres (> 0).
        cam_to_opt: 4x4 rigid transform from this frame's OpenCV left camera to the optimisation
            frame (x right, y down along gravity, z forward).
        depth: optional precomputed HxW depth in metres (0 or NaN = invalid).
        frame_index: absolute frame index (names the file of a depth directory; optional).
    """

    frame_offset: int
    left: np.ndarray
    right: np.ndarray | None
    masks: dict[int, np.ndarray]
    K: np.ndarray
    baseline: float
    cam_to_opt: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth: np.ndarray | None = None
    frame_index: int | None = None

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.cam_to_opt = np.asarray(self.cam_to_opt, dtype=np.float64).reshape(4, 4)
        self.baseline = float(self.baseline)
        if self.left.ndim != 3 or self.left.shape[2] != 3 or self.left.dtype != np.uint8:
            raise ValueError(f"left image must be HxWx3 uint8, got {self.left.shape} {self.left.dtype}")
        shape = self.left.shape[:2]
        if self.right is not None and (self.right.shape != self.left.shape
                                       or self.right.dtype != np.uint8):
            raise ValueError(f"right image {self.right.shape} {self.right.dtype} does not match "
                             f"left image {self.left.shape} uint8")
        if self.right is None and self.depth is None:
            raise ValueError("a frame needs a right image or a precomputed depth map")
        if self.depth is not None and self.depth.shape != shape:
            raise ValueError(f"depth map {self.depth.shape} does not match the image {shape}")
        for iid, m in self.masks.items():
            if m.shape != shape or m.dtype != bool:
                raise ValueError(f"mask of instance {iid} must be a {shape} bool array, "
                                 f"got {m.shape} {m.dtype}")
        if not (self.baseline > 0 and np.isfinite(self.baseline)):
            raise ValueError(f"baseline must be a positive number, got {self.baseline}")
        if not (np.all(np.isfinite(self.K)) and np.all(np.isfinite(self.cam_to_opt))):
            raise ValueError("K and cam_to_opt must be finite")

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of the images."""
        return int(self.left.shape[1]), int(self.left.shape[0])

    @property
    def camera_centre(self) -> np.ndarray:
        """Centre of the left camera in the optimisation frame."""
        return self.cam_to_opt[:3, 3].copy()
