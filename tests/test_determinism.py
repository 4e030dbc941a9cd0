"""Same seed, same labels: two runs of one target write identical label files."""

from __future__ import annotations

import json
from pathlib import Path

from vsrd_mi.autolabel.job import process_target
from vsrd_mi.batch.tasks import TargetTask
from vsrd_mi.optimise.config import default_config

ROOT = Path(__file__).resolve().parents[1] / "scenes" / "kitti360-synth"
SEQUENCE = "2013_05_28_drive_0000_sync"


def test_two_runs_of_a_target_write_identical_labels(tmp_path):
    # the whole default run (440 steps on this target): rounding differences would grow over it
    cfg = default_config().to_dict()
    outs = []
    for run in ("a", "b"):
        task = TargetTask(root=str(ROOT), sequence=SEQUENCE, frame=21, output_dir=str(tmp_path / run),
                          config=cfg, seed=3)
        assert process_target(task).status == "done"
        outs.append(tmp_path / run / SEQUENCE)
    labels = sorted(p.name for p in (outs[0] / "labels").iterdir())
    assert labels and labels == sorted(p.name for p in (outs[1] / "labels").iterdir())
    for name in labels:
        assert (outs[0] / "labels" / name).read_bytes() == (outs[1] / "labels" / name).read_bytes(), name
    boxes = [json.loads((out / "boxes" / "0000000021.json").read_text()) for out in outs]
    assert boxes[0]["boxes"] == boxes[1]["boxes"] and boxes[0]["loss"] == boxes[1]["loss"]
    # each box says how its length was set: lengthened past an end held from inside, or (an
    # option, off by default) from the prior where no view measured it
    assert all(isinstance(b["length_held_from_inside"], bool) and b["length_unmeasured"] is False
               for b in boxes[0]["boxes"])
    # and whether the length prior held it: the moving car ahead in the lane, seen end-on
    assert [b["instance_id"] for b in boxes[0]["boxes"] if b["length_from_prior"]] == [26002]
