"""A detector's training set from autolabel runs: the KITTI object-detection layout
(``vsrd-mi export-dataset``; layout, calib and ``--level`` in ``docs/export.md``).

::

    OUT/training/image_2/%06d.png   the frame's left rectified image (relative symlink, copy, or
                                    with level=True the level camera's image)
    OUT/training/calib/%06d.txt     :mod:`.calib` (P2 = the camera of the labels)
    OUT/training/label_2/%06d.txt   the run's labels of the frame, score = confidence
                                    (lines with score < min_score left out)
    OUT/ImageSets/train.txt, val.txt, trainval.txt (%06d per line), test.txt (empty: no test split)
    OUT/mapping.txt                 line i: "<sequence> <frame>" of index i
    OUT/export.json                 provenance: options, per index the run, dataset root, files

A run is an ``autolabel --out`` folder (``RUN/<sequence>/labels/%010d.txt``) or one of its
sequence folders; every labelled frame of every run appears once, indices ordered by
(sequence, frame). The dataset roots hold the images and calibration: one root for all runs, or
one per run in order.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..data.kitti360 import (
    Calibration,
    frame_file,
    image_dir,
    read_calibration,
    read_cam0_to_world,
)
from ..data.kitti_labels import KittiLabel, read_labels, write_labels
from ..data.png import read_png
from ..errors import DataError
from .calib import calib_for_frame, write_calib
from .level import level_image, level_labels, level_rotation, pitch_roll_deg

#: Label files of a run: the frame index, zero-padded to 10 digits.
RUN_LABEL_FILE = re.compile(r"^(\d{10})\.txt$")
#: Digits of an exported index (``%06d``).
INDEX_DIGITS = 6

SPLIT_FRAMES, SPLIT_SEQUENCES = "frames", "sequences"
DUPLICATES_ERROR, DUPLICATES_FIRST = "error", "first"

#: What the export creates under OUT (``force`` removes exactly these before writing).
CREATED = ("training", "ImageSets", "mapping.txt", "export.json")


@dataclass(frozen=True)
class ExportConfig:
    """Options of :func:`export_dataset`."""

    #: Label lines with a score below this are left out (lines without a score count as 1).
    min_score: float = 0.0
    #: Share of the frames (``split_by="frames"``: the last frames of each sequence, a contiguous
    #: block so neighbouring near-identical frames do not straddle the split) or of the sequences
    #: (``"sequences"``: the last ones in name order) that go to ``val.txt``.
    val_fraction: float = 0.2
    split_by: str = SPLIT_FRAMES
    #: Sequences that form the validation split (overrides ``val_fraction`` / ``split_by``).
    val_sequences: tuple[str, ...] = ()
    #: Copy the images instead of linking them (relative symlinks).
    copy_images: bool = False
    #: Write every frame in its level camera (:mod:`.level`): warped images, level labels and calib.
    level: bool = False
    #: Leave out frames with no label line left (after ``min_score``).
    skip_empty: bool = False
    #: A (sequence, frame) labelled by several runs: an error, or the first run listed wins.
    duplicates: str = DUPLICATES_ERROR
    #: Replace an earlier export in OUT (removes only what the export creates: :data:`CREATED`).
    force: bool = False

    def __post_init__(self) -> None:
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.split_by not in (SPLIT_FRAMES, SPLIT_SEQUENCES):
            raise ValueError(f"split_by must be {SPLIT_FRAMES!r} or {SPLIT_SEQUENCES!r}, got {self.split_by!r}")
        if self.duplicates not in (DUPLICATES_ERROR, DUPLICATES_FIRST):
            raise ValueError(f"duplicates must be {DUPLICATES_ERROR!r} or {DUPLICATES_FIRST!r}")


@dataclass(frozen=True)
class LabelledFrame:
    """One labelled frame of a run and where its data lives."""

    sequence: str
    frame: int
    label_path: Path
    run: Path
    root: Path

    @property
    def image_path(self) -> Path:
        return frame_file(image_dir(self.root, self.sequence, 0), self.frame)


def run_sequence_dirs(run: str | os.PathLike) -> list[Path]:
    """The sequence folders of a run: ``run`` itself when it holds ``labels/``, else its
    sub-folders that do. DataError naming ``run`` when there is none."""
    run = Path(run)
    if not run.is_dir():
        raise DataError(run, "missing run folder")
    if (run / "labels").is_dir():
        return [run]
    dirs = sorted(p for p in run.iterdir() if (p / "labels").is_dir())
    if not dirs:
        raise DataError(run, "no labels/ folder: not an autolabel run (expected RUN/<sequence>/labels/%010d.txt)")
    return dirs


def run_frames(run: str | os.PathLike, root: str | os.PathLike) -> list[LabelledFrame]:
    """Every labelled frame of ``run`` (label files ``%010d.txt``) with its dataset ``root``."""
    frames = []
    for seq_dir in run_sequence_dirs(run):
        label_dir = seq_dir / "labels"
        files = sorted((int(m.group(1)), p) for p in label_dir.iterdir()
                       if (m := RUN_LABEL_FILE.match(p.name)) and p.is_file())
        if not files:
            raise DataError(label_dir, "no label files (%010d.txt): the run labelled nothing here")
        frames += [LabelledFrame(seq_dir.name, f, p, Path(run), Path(root)) for f, p in files]
    return frames


def collect_frames(runs: Sequence[str | os.PathLike], roots: Sequence[str | os.PathLike],
                   duplicates: str = DUPLICATES_ERROR) -> list[LabelledFrame]:
    """The labelled frames of all ``runs``, ordered by (sequence, frame), each once.

    ``roots`` holds one dataset root for all runs or one per run. A sequence name met under two
    different roots is an error (its frames could not be told apart in ``mapping.txt``); so is a
    frame labelled by two runs unless ``duplicates="first"``.
    """
    if not runs:
        raise ValueError("no run given")
    if len(roots) not in (1, len(runs)):
        raise ValueError(f"give one dataset root for all runs or one per run: {len(runs)} runs, {len(roots)} roots")
    roots = list(roots) * len(runs) if len(roots) == 1 else list(roots)
    chosen: dict[tuple[str, int], LabelledFrame] = {}
    seq_roots: dict[str, Path] = {}
    for run, root in zip(runs, roots):
        for lf in run_frames(run, root):
            known = seq_roots.setdefault(lf.sequence, Path(root).resolve())
            if known != Path(root).resolve():
                raise DataError(lf.run, f"sequence {lf.sequence} comes from two dataset roots ({known} and "
                                        f"{Path(root).resolve()}): export them separately")
            key = (lf.sequence, lf.frame)
            if key in chosen:
                if duplicates == DUPLICATES_ERROR:
                    raise DataError(lf.label_path, f"frame {lf.frame} of {lf.sequence} is also labelled by "
                                                   f"{chosen[key].label_path} (pass duplicates='first' / "
                                                   f"--duplicates first to keep the first run's)")
                continue
            chosen[key] = lf
    return [chosen[k] for k in sorted(chosen)]


def validation_indices(frames: Sequence[LabelledFrame], cfg: ExportConfig) -> set[int]:
    """Indices (into ``frames``) of the validation split (see :class:`ExportConfig`)."""
    sequences = sorted({f.sequence for f in frames})
    if cfg.val_sequences:
        unknown = sorted(set(cfg.val_sequences) - set(sequences))
        if unknown:
            raise ValueError(f"validation sequences {unknown} are not among the runs' sequences {sequences}")
        return {i for i, f in enumerate(frames) if f.sequence in cfg.val_sequences}
    if cfg.val_fraction == 0.0:
        return set()
    if cfg.split_by == SPLIT_SEQUENCES:
        if len(sequences) < 2:
            raise ValueError(f"a split by sequences needs at least two sequences, the runs hold {sequences}")
        n_val = min(len(sequences) - 1, max(1, round(cfg.val_fraction * len(sequences))))
        val = set(sequences[len(sequences) - n_val:])
        return {i for i, f in enumerate(frames) if f.sequence in val}
    out: set[int] = set()
    for seq in sequences:
        idx = [i for i, f in enumerate(frames) if f.sequence == seq]
        n_val = min(len(idx) - 1, round(cfg.val_fraction * len(idx)))
        out.update(idx[len(idx) - n_val:] if n_val > 0 else [])
    return out


def kept_labels(lf: LabelledFrame, min_score: float) -> list[KittiLabel]:
    """The frame's label lines with score >= ``min_score`` (a line without a score counts as 1)."""
    return [lab for lab in read_labels(lf.label_path) if (1.0 if lab.score is None else lab.score) >= min_score]


def prepare_output(out: Path, force: bool) -> None:
    """Make sure ``out`` can take a new export (see :data:`CREATED`)."""
    existing = [name for name in CREATED if (out / name).exists() or (out / name).is_symlink()]
    if existing and not force:
        raise DataError(out, f"already holds an export ({', '.join(existing)}); choose another folder or force")
    for name in existing:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    for sub in ("training/image_2", "training/calib", "training/label_2", "ImageSets"):
        (out / sub).mkdir(parents=True, exist_ok=True)


def place_image(src: Path, dst: Path, copy: bool) -> None:
    """``dst`` becomes a relative symlink to ``src`` or a copy of it."""
    if copy:
        shutil.copyfile(src, dst)
    else:
        os.symlink(os.path.relpath(src.resolve(), dst.parent.resolve()), dst)


def _index_name(i: int) -> str:
    return f"{i:0{INDEX_DIGITS}d}"


def export_dataset(out: str | os.PathLike, runs: Sequence[str | os.PathLike], roots: Sequence[str | os.PathLike],
                   cfg: ExportConfig = ExportConfig()) -> dict:
    """Write the KITTI layout of the runs' labelled frames under ``out``; returns the summary
    also written to ``out/export.json``. Bad input (a run without labels, a missing image or
    calibration, a malformed label file) raises DataError naming it before anything is written."""
    out = Path(out)
    frames = collect_frames(runs, roots, cfg.duplicates)
    labels = [kept_labels(lf, cfg.min_score) for lf in frames]
    if cfg.skip_empty:
        frames, labels = [f for f, lab in zip(frames, labels) if lab], [lab for lab in labels if lab]
    if not frames:
        raise DataError(Path(runs[0]), f"no frame left to export (min_score {cfg.min_score}, skip_empty)")
    calibrations: dict[Path, Calibration] = {}
    poses: dict[tuple[Path, str], dict[int, np.ndarray]] = {}
    for lf in frames:
        if not lf.image_path.is_file():
            raise DataError(lf.image_path, f"missing image of frame {lf.frame} of {lf.sequence} "
                                           f"(labels: {lf.label_path})")
        if lf.root not in calibrations:
            calibrations[lf.root] = read_calibration(lf.root)
        if cfg.level:
            if (lf.root, lf.sequence) not in poses:
                poses[(lf.root, lf.sequence)] = read_cam0_to_world(lf.root, lf.sequence, calibrations[lf.root])
            if lf.frame not in poses[(lf.root, lf.sequence)]:
                raise DataError(lf.root / "data_poses" / lf.sequence,
                                f"no pose for frame {lf.frame}: --level needs it")
    val = validation_indices(frames, cfg)
    prepare_output(out, cfg.force)
    entries = []
    for i, (lf, frame_labels) in enumerate(zip(frames, labels)):
        name = _index_name(i)
        calibration = calibrations[lf.root]
        image_out = out / "training" / "image_2" / f"{name}.png"
        entry = {"index": name, "sequence": lf.sequence, "frame": lf.frame, "split": "val" if i in val else "train",
                 "run": str(lf.run), "root": str(lf.root), "labels_from": str(lf.label_path),
                 "image_from": str(lf.image_path), "n_labels": len(frame_labels)}
        R = None
        if cfg.level:
            R = level_rotation(poses[(lf.root, lf.sequence)][lf.frame])
            image = read_png(lf.image_path, dtype=np.uint8, channels=3, size=calibration.image_size, what="image")
            K = calibration.P_rect_00[:3, :3]
            frame_labels, dropped = level_labels(frame_labels, R, K, calibration.image_size)
            if not cv2.imwrite(str(image_out), cv2.cvtColor(level_image(image, K, R), cv2.COLOR_RGB2BGR)):
                raise DataError(image_out, "cannot write the level image")
            pitch, roll = pitch_roll_deg(R)
            entry.update(n_labels=len(frame_labels), labels_outside_level_image=dropped, pitch_deg=pitch,
                         roll_deg=roll)
        else:
            place_image(lf.image_path, image_out, cfg.copy_images)
        write_calib(out / "training" / "calib" / f"{name}.txt", calib_for_frame(calibration, R))
        write_labels(out / "training" / "label_2" / f"{name}.txt", frame_labels)
        entries.append(entry)
    _write_lines(out / "mapping.txt", [f"{e['sequence']} {e['frame']}" for e in entries])
    splits = {"train": [e["index"] for e in entries if e["split"] == "train"],
              "val": [e["index"] for e in entries if e["split"] == "val"]}
    _write_lines(out / "ImageSets" / "train.txt", splits["train"])
    _write_lines(out / "ImageSets" / "val.txt", splits["val"])
    _write_lines(out / "ImageSets" / "trainval.txt", [e["index"] for e in entries])
    _write_lines(out / "ImageSets" / "test.txt", [])
    summary = {"format": "vsrd-mi export 1", "config": asdict(cfg), "n_frames": len(entries),
               "n_train": len(splits["train"]), "n_val": len(splits["val"]),
               "n_labels": int(sum(e["n_labels"] for e in entries)),
               "sequences": sorted({e["sequence"] for e in entries}), "frames": entries}
    (out / "export.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    return summary


def _write_lines(path: Path, lines: Sequence[str]) -> None:
    path.write_text("".join(f"{line}\n" for line in lines), encoding="ascii")
