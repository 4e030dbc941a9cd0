"""KITTI-360 label ids of cars and how instance-map values encode them (docs/method.md §8)."""

from __future__ import annotations

#: KITTI-360 label id of "car" (the value used in instance maps: ``26 * 1000 + instanceId``).
CAR_LABEL_ID = 26
#: The "KITTI id" of "car", which is what the 3D-box XML stores in ``semanticId``.
CAR_KITTI_ID = 13
#: Instance-map values are ``label_id * INSTANCE_FACTOR + instance_id``.
INSTANCE_FACTOR = 1000
#: KITTI-360 label ids of what can stand in front of a car and hide part of it: pole (17),
#: polegroup (18), traffic light (19), traffic sign (20), vegetation (21), person (24), rider (25),
#: car (26), truck (27), bus (28), caravan (29), trailer (30), train (31), motorcycle (32), bicycle
#: (33), stop (36), smallpole (37), lamp (38), trash bin (39), vending machine (40), box (41),
#: unknown vehicle (43), unknown object (44). Road, sidewalk, buildings and other constructions,
#: terrain and sky lie behind the cars of a street (KITTI-360's label table, ``labels.py`` of its
#: development scripts).
OCCLUDING_LABEL_IDS = (17, 18, 19, 20, 21, 24, 25, 26, 27, 28, 29, 30, 31, 32, 33, 36, 37, 38, 39, 40,
                       41, 43, 44)


def car_instance_value(instance_id: int) -> int:
    """Instance-map pixel value of the car with dataset ``instanceId`` (``26 * 1000 + instanceId``)."""
    return CAR_LABEL_ID * INSTANCE_FACTOR + int(instance_id)
