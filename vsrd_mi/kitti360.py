"""KITTI-360 entry points: ``load_scene(root, sequence, frame)`` and the sequence reader."""

from .data.kitti360 import Calibration, Sequence, read_calibration, sequence_name
from .scene.builder import load_scene, save_scene_xml

__all__ = ["load_scene", "save_scene_xml", "Sequence", "Calibration", "read_calibration", "sequence_name"]
