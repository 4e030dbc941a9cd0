"""KITTI-360 label ids of cars and how instance-map values encode them (docs/method.md §8)."""

from __future__ import annotations

#: KITTI-360 label id of "car" (the value used in instance maps: ``26 * 1000 + instanceId``).
CAR_LABEL_ID = 26
#: The "KITTI id" of "car", which is what the 3D-box XML stores in ``semanticId``.
CAR_KITTI_ID = 13
#: Instance-map values are ``label_id * INSTANCE_FACTOR + instance_id``.
INSTANCE_FACTOR = 1000


def car_instance_value(instance_id: int) -> int:
    """Instance-map pixel value of the car with dataset ``instanceId`` (``26 * 1000 + instanceId``)."""
    return CAR_LABEL_ID * INSTANCE_FACTOR + int(instance_id)
