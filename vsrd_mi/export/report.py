"""A review page of an autolabel run: ``vsrd-mi report RUN`` writes ``RUN/report/index.html``.

The page is self-contained: plain HTML with inline CSS, every image and link relative, so it opens
from disk (or from any copy of the run folder). Per sequence of the run it shows

* the summary: targets done / failed / skipped (``manifest.json``), optimisation time, the
  settings (the targets' configuration; keys that differ between targets are listed), failed
  targets' errors and the consensus of parked cars (``consensus.json``);
* the evaluation summary (:func:`vsrd_mi.evaluate.evaluate_sequence`, default protocol) when the
  dataset is given and has ground truth;
* per target: a table of its boxes (size, yaw, velocity, confidence, and the 3D IoU with the
  matched ground truth when there is one) with boxes below ``review_below`` confidence flagged for
  review, the loss summary, and the visuals: those of ``autolabel --vis`` (projected boxes on the
  target and source images, rendered vs real masks, bird's-eye view, loss curves, meshes) when the
  target has a ``vis/`` folder, otherwise the projected boxes and bird's-eye view rendered from the
  result file and the dataset (:mod:`.report_render`), or a note saying what is missing.

A script at the end of the page writes into it how many of its images the browser drew.
"""

from __future__ import annotations

import html
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..autolabel.visualise import VisualConfig
from ..data.kitti360 import Sequence as KittiSequence
from ..errors import DataError
from ..evaluate.metrics import hungarian_pairs
from ..evaluate.sequence import evaluate_sequence
from ..geometry.boxes import Box3D
from .dataset import run_sequence_dirs
from .report_render import ground_truth_in_opt, render_target

#: The report's folder inside the run, and its page.
REPORT_DIR, REPORT_PAGE = "report", "index.html"

#: ``--vis`` files shown per target (file name, caption), in page order.
VIS_FIGURES = (("boxes_target.png", "optimised boxes projected onto the target image"),
               ("boxes_sources.png", "the same boxes on the source images"),
               ("masks.png", "real instance masks (left) and the rendered soft masks (right)"),
               ("bev.png", "bird's-eye view: optimised boxes in colour, ground truth in white"),
               ("loss.png", "loss history"))
#: Captions of the figures rendered without ``--vis``.
RENDERED_CAPTIONS = {"boxes_target": "boxes projected onto the target image (rendered from the result file)",
                     "boxes_sources": "the same boxes on source images",
                     "bev": "bird's-eye view: boxes in colour, ground truth in white"}


@dataclass(frozen=True)
class ReportConfig:
    """Options of :func:`write_report`."""

    #: Boxes whose confidence is below this are flagged for review (the confidence is the mean 2D
    #: IoU of the box's projections with the instance's mask boxes over the target's group).
    review_below: float = 0.5
    #: Evaluate the run against the dataset's ground truth when it has some.
    evaluate: bool = True
    #: Source frames drawn per target when the visuals are rendered here (no ``vis/`` folder).
    rendered_sources: int = 4
    #: Sizes of the rendered visuals.
    visuals: VisualConfig = field(default_factory=VisualConfig)


@dataclass
class TargetEntry:
    """What the run holds about one target frame."""

    frame: int
    status: str
    manifest: dict
    result_path: Path | None = None
    result: dict | None = None
    vis_dir: Path | None = None


def _esc(value) -> str:
    return html.escape(str(value), quote=True)


def _num(value, spec: str = ".3f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, spec)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(path, f"unreadable: {exc}") from None


def read_targets(seq_dir: Path) -> tuple[list[TargetEntry], dict | None]:
    """The targets of a run's sequence folder (manifest entries and result files) and its
    manifest (None when absent). Targets with a result file but no manifest entry count as done."""
    manifest_path = seq_dir / "manifest.json"
    manifest = _read_json(manifest_path) if manifest_path.is_file() else None
    entries: dict[int, TargetEntry] = {}
    for key, m in (manifest or {}).get("targets", {}).items():
        entries[int(key)] = TargetEntry(int(key), str(m.get("status", "unknown")), m)
    for path in sorted((seq_dir / "boxes").glob("*.json")) if (seq_dir / "boxes").is_dir() else []:
        if not path.stem.isdigit():
            continue
        entry = entries.setdefault(int(path.stem), TargetEntry(int(path.stem), "done", {}))
        entry.result_path, entry.result = path, _read_json(path)
    for entry in entries.values():
        vis = seq_dir / "vis" / f"{entry.frame:010d}"
        entry.vis_dir = vis if vis.is_dir() else None
    return [entries[k] for k in sorted(entries)], manifest


def _status_counts(targets: Sequence[TargetEntry]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for t in targets:
        counts[t.status] = counts.get(t.status, 0) + 1
    return counts


def _settings(targets: Sequence[TargetEntry]) -> tuple[dict, list[str]]:
    """The first target's configuration and the top-level keys whose values differ between targets."""
    configs = [t.result.get("config", {}) for t in targets if t.result]
    if not configs:
        return {}, []
    differ = sorted(k for k in configs[0] if any(json.dumps(c.get(k), sort_keys=True)
                                                 != json.dumps(configs[0][k], sort_keys=True) for c in configs))
    return configs[0], differ


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "",
           row_classes: Sequence[str] | None = None) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = []
    for i, row in enumerate(rows):
        rc = f' class="{row_classes[i]}"' if row_classes and row_classes[i] else ""
        body.append(f"<tr{rc}>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>")
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def _rel(path: Path, page_dir: Path) -> str:
    """URL of ``path`` relative to the page's folder (forward slashes, escaped)."""
    return _esc(Path(os.path.relpath(path.resolve(), page_dir.resolve())).as_posix())


def _figure(path: Path, page_dir: Path, caption: str) -> str:
    return (f'<figure><a href="{_rel(path, page_dir)}"><img src="{_rel(path, page_dir)}" alt="{_esc(caption)}"></a>'
            f"<figcaption>{_esc(caption)}</figcaption></figure>")


# ----------------------------------------------------------------------------------------------
# Sequence summary and evaluation
# ----------------------------------------------------------------------------------------------


def summary_html(seq_dir: Path, targets: Sequence[TargetEntry], manifest: dict | None) -> str:
    """The summary block of one sequence: targets by status, time, settings, failures, consensus."""
    counts = _status_counts(targets)
    parts = [f"<p><b>{len(targets)}</b> target(s): " + ", ".join(f"{_esc(k)} {v}" for k, v in sorted(counts.items()))
             + ("" if manifest else " (no manifest.json: only the result files are known)") + "</p>"]
    seconds = [float(t.manifest["seconds"]) for t in targets if t.manifest.get("seconds") is not None]
    started = sorted(t.manifest["started"] for t in targets if t.manifest.get("started"))
    finished = sorted(t.manifest["finished"] for t in targets if t.manifest.get("finished"))
    steps = [int(t.result["steps"]) for t in targets if t.result and "steps" in t.result]
    facts = [("optimisation time", f"{sum(seconds):.1f} s over {len(seconds)} target(s)" if seconds else "-"),
             ("first start / last finish", f"{started[0]} / {finished[-1]}" if started and finished else "-"),
             ("steps per target", f"{min(steps)}-{max(steps)} (mean {np.mean(steps):.0f})" if steps else "-")]
    config, differ = _settings(targets)
    scalar = {k: v for k, v in config.items() if not isinstance(v, (dict, list))}
    facts.append(("settings", ", ".join(f"{_esc(k)}={_esc(v)}" for k, v in sorted(scalar.items())) or "-"))
    if differ:
        facts.append(("settings that differ between targets", _esc(", ".join(differ))))
    parts.append(_table(["", ""], [[_esc(k), v] for k, v in facts], "facts"))
    if config:
        parts.append(f"<details><summary>full configuration (first target)</summary><pre>"
                     f"{_esc(json.dumps(config, indent=1, sort_keys=True))}</pre></details>")
    failed = [t for t in targets if t.status == "failed"]
    if failed:
        rows = [[str(t.frame), _esc(json.dumps(t.manifest.get("error"), indent=None))] for t in failed]
        parts.append("<h4>Failed targets</h4>" + _table(["target", "error"], rows, "failed"))
    consensus_path = seq_dir / "consensus.json"
    if consensus_path.is_file():
        c = _read_json(consensus_path)
        fused = c.get("fused", [])
        parts.append(f"<p>Consensus of parked cars: {'on' if c.get('enabled') else 'off'}; {len(fused)} car(s) "
                     f"fused over {len(c.get('targets', []))} target(s), {len(c.get('labels_rewritten', []))} "
                     f"label file(s) rewritten" + "".join(f"; left out: {_esc(s)}" for s in c.get("skipped", []))
                     + "</p>")
    return "\n".join(parts)


def evaluation_html(result: dict) -> str:
    """AP / AOS and matched-pair tables of an :func:`evaluate_sequence` result."""
    protocol = result["protocol"]
    rows = []
    for metric, label in (("bev", "AP_BEV"), ("3d", "AP_3D")):
        for thr, by_diff in result["ap"][metric].items():
            rows.append([f"{label}@{thr}"] + [_num(by_diff[d][k], ".2f") for k in ("R40", "AOS_R40")
                                              for d in ("easy", "hard")])
    ap = _table(["", "AP Easy R40", "AP Hard R40", "AOS Easy R40", "AOS Hard R40"], rows, "eval")
    pair_rows = [[_esc(g), str(s["n_gt"]), str(s["n_cars"]), str(s["n_matched"]), _num(s["missed_share"], ".0%"),
                  _num(s["mean_iou_3d"]), _num(s["mean_iou_bev"]), _num(s["centre_error_m"]),
                  _num(s["yaw_error_deg"], ".1f"), _num(s["heading_accuracy"], ".0%")]
                 for g, s in result["pairs"].items()]
    pairs = _table(["group", "GT", "cars", "matched", "without box", "mean IoU 3D", "mean IoU BEV", "centre error m",
                    "yaw error deg (mod 180)", "heading right"], pair_rows, "eval")
    return (f"<p>{len(result['frames'])} frame(s) evaluated; ground-truth 2D boxes: "
            f"<b>{_esc(protocol['gt_boxes'])}</b> "
            f"({_esc(protocol['gt_boxes_rule'])}); exact precision curve.</p>{ap}{pairs}")


def try_evaluate(seq_dir: Path, seq: KittiSequence | None) -> str:
    """The evaluation block of a sequence, or a note saying why there is none."""
    if seq is None:
        return "<p>No evaluation: no dataset given (<code>--root</code>).</p>"
    if not seq.has_boxes:
        return "<p>No evaluation: the dataset has no 3D ground truth for this sequence.</p>"
    try:
        return evaluation_html(evaluate_sequence(seq_dir / "labels", seq.root, seq.name))
    except DataError as exc:
        return f"<p>No evaluation: {_esc(exc)}</p>"


# ----------------------------------------------------------------------------------------------
# Targets
# ----------------------------------------------------------------------------------------------


def ground_truth_ious(seq: KittiSequence | None, target: int, boxes: Sequence[Box3D]) -> list[float | None]:
    """3D IoU of each box with its Hungarian-matched ground truth in the target frame (None
    without ground truth or match)."""
    if seq is None or not seq.has_boxes:
        return [None] * len(boxes)
    out: list[float | None] = [None] * len(boxes)
    for _, j, _, iou3d in hungarian_pairs(ground_truth_in_opt(seq, target), boxes):
        out[j] = iou3d
    return out


def boxes_table(result: dict, ious: Sequence[float | None], review_below: float) -> str:
    """Table of a target's boxes; rows under ``review_below`` confidence flagged."""
    rows, classes = [], []
    for b, iou in zip(result.get("boxes", []), ious):
        w, h, l = b["size"]  # noqa: E741
        v = np.asarray(b.get("velocity", (0.0, 0.0, 0.0)), dtype=float)
        conf = float(b["confidence"])
        review = conf < review_below
        rows.append([_esc(b.get("instance_id", "-")), "moving" if b.get("dynamic") else "parked",
                     f"{l:.2f} x {w:.2f} x {h:.2f}", f"{math.degrees(float(b['yaw'])):.1f}",
                     f"{np.linalg.norm(v):.3f} ({v[0]:+.2f}, {v[2]:+.2f})", f"{conf:.3f}", _num(iou),
                     "<b>review</b>" if review else ""])
        classes.append("review" if review else "")
    return _table(["instance", "kind", "size l x w x h (m)", "yaw (deg)", "velocity m/frame (x, z)",
                   "confidence", "3D IoU vs GT", f"flag (< {review_below:g})"], rows, "boxes", classes)


def loss_table(result: dict) -> str:
    rows = [[_esc(k), _num(v.get("first"), ".4g"), _num(v.get("last"), ".4g"), _num(v.get("min"), ".4g")]
            for k, v in result.get("loss", {}).items()]
    return _table(["loss term", "first", "last", "min"], rows, "loss") if rows else ""


def target_visuals(entry: TargetEntry, seq: KittiSequence | None, page_dir: Path, cfg: ReportConfig) -> str:
    """Figures of one target: the ``--vis`` files, or rendered ones, or a note."""
    if entry.vis_dir is not None:
        figs = [_figure(entry.vis_dir / name, page_dir, cap) for name, cap in VIS_FIGURES
                if (entry.vis_dir / name).is_file()]
        meshes = sorted((entry.vis_dir / "meshes").glob("*.ply")) if (entry.vis_dir / "meshes").is_dir() else []
        links = ("<p>meshes (PLY): " + ", ".join(f'<a href="{_rel(m, page_dir)}">{_esc(m.name)}</a>' for m in meshes)
                 + "</p>") if meshes else ""
        return f'<div class="figs">{"".join(figs)}</div>{links}'
    if seq is None:
        return ("<p>No visuals: this target has no <code>vis/</code> folder (run <code>autolabel --vis</code>) "
                "and no dataset was given (<code>--root</code>) to render them from.</p>")
    try:
        files = render_target(page_dir / seq.name / f"{entry.frame:010d}", seq, entry.result_path,
                              entry.result.get("sources", []), cfg.rendered_sources, cfg.visuals)
    except DataError as exc:
        return f"<p>No visuals: {_esc(exc)}</p>"
    figs = [_figure(path, page_dir, RENDERED_CAPTIONS[name]) for name, path in files.items()]
    return (f'<div class="figs">{"".join(figs)}</div><p class="note">No <code>vis/</code> folder: rendered from '
            f"the result file and the dataset; the rendered-vs-real masks and loss curves need "
            f"<code>autolabel --vis</code>.</p>")


def target_html(entry: TargetEntry, seq: KittiSequence | None, page_dir: Path, cfg: ReportConfig) -> str:
    """The section of one target."""
    anchor = f"{seq.name if seq else 'seq'}-{entry.frame}"
    status = _esc(entry.status)
    head = f'<h3 id="{_esc(anchor)}">Target {entry.frame} <span class="status {status}">{status}</span></h3>'
    r = entry.result
    if r is None:
        error = entry.manifest.get("error")
        return head + (f"<p>No result file. Error: <code>{_esc(json.dumps(error))}</code></p>" if error
                       else "<p>No result file.</p>")
    group = r.get("group", [])
    span = f"{min(group)}-{max(group)}" if group else "-"
    facts = (f"<p>{r.get('steps', '-')} steps in {_num(r.get('seconds'), '.1f')} s"
             f"{' (stopped early)' if r.get('stopped_early') else ''}; labelled frames {_esc(span)} ({len(group)}); "
             f"{len(r.get('sources', []))} source frames; {_esc(r.get('initialisation', '-'))}</p>")
    boxes = [Box3D.from_dict(b) for b in r.get("boxes", [])]
    table = boxes_table(r, ground_truth_ious(seq, entry.frame, boxes), cfg.review_below)
    warnings = r.get("visuals", {}).get("warnings", [])
    warn = "".join(f'<p class="note">visual warning: {_esc(w)}</p>' for w in warnings)
    return head + facts + table + loss_table(r) + target_visuals(entry, seq, page_dir, cfg) + warn


# ----------------------------------------------------------------------------------------------
# Page
# ----------------------------------------------------------------------------------------------

STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1500px; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #eee; } td:first-child { text-align: left; }
tr.review td { background: #ffe0e0; }
.figs { display: flex; flex-wrap: wrap; gap: 10px; }
figure { margin: 0; flex: 1 1 560px; max-width: 720px; } figure img { width: 100%; border: 1px solid #999; }
table.facts td { text-align: left; }
figcaption { font-size: 0.85em; color: #555; }
.status { font-size: 0.7em; padding: 1px 6px; border-radius: 4px; background: #ddd; }
.status.done { background: #cfc; } .status.failed { background: #fcc; }
.note { color: #666; font-size: 0.9em; } section.target { border-top: 1px solid #bbb; margin-top: 1.5em; }
"""

IMAGE_CHECK = """
<p id="image-check" class="note">images: not checked (scripts off)</p>
<script>
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
  var el = document.getElementById("image-check");
  el.textContent = "images: " + (imgs.length - bad.length) + " of " + imgs.length + " drawn" +
    (bad.length ? "; not drawn: " + bad.map(function (i) { return i.getAttribute("src"); }).join(", ") : "");
  el.setAttribute("data-drawn", String(imgs.length - bad.length));
  el.setAttribute("data-total", String(imgs.length));
});
</script>
"""


def write_report(run: str | Path, root: str | Path | None = None, cfg: ReportConfig = ReportConfig()) -> Path:
    """Write ``run/report/index.html`` (module docstring) and return its path.

    ``root`` is the KITTI-360 root of the run's sequences (None: no evaluation and no rendered
    visuals). Raises DataError naming ``run`` when it holds no labelled sequence.
    """
    run = Path(run)
    page_dir = run / REPORT_DIR
    page_dir.mkdir(parents=True, exist_ok=True)
    sections, toc = [], []
    for seq_dir in run_sequence_dirs(run):
        targets, manifest = read_targets(seq_dir)
        seq = KittiSequence(root, seq_dir.name) if root is not None else None
        flagged = sum(1 for t in targets if t.result for b in t.result.get("boxes", [])
                      if float(b["confidence"]) < cfg.review_below)
        toc.append(f'<li><a href="#{_esc(seq_dir.name)}">{_esc(seq_dir.name)}</a>: {len(targets)} target(s), '
                   f"{flagged} box(es) to review</li>")
        body = [f'<h2 id="{_esc(seq_dir.name)}">{_esc(seq_dir.name)}</h2>', summary_html(seq_dir, targets, manifest),
                "<h3>Evaluation</h3>", try_evaluate(seq_dir, seq) if cfg.evaluate else "<p>Evaluation off.</p>"]
        body += [f'<section class="target">{target_html(t, seq, page_dir, cfg)}</section>' for t in targets]
        sections.append("\n".join(body))
    page = (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>vsrd-mi report: {_esc(run.name)}</title>"
            f"<style>{STYLE}</style></head><body><h1>Autolabel run {_esc(run.resolve())}</h1>"
            f"<p>Dataset: {_esc(Path(root).resolve()) if root is not None else 'not given'}. Boxes with confidence "
            f"below {cfg.review_below:g} are flagged for review.</p><ul>{''.join(toc)}</ul>"
            + "\n".join(sections) + IMAGE_CHECK + "</body></html>\n")
    path = page_dir / REPORT_PAGE
    path.write_text(page, encoding="utf-8")
    return path