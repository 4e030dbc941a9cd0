"""Small real jobs for the batch tests (a module, so Dask worker processes can import it).

``digest_job`` draws ``config["n"]`` normal samples from a generator seeded by (seed, frame),
writes them to ``samples/<frame>.npy`` and their statistics to ``stats/<frame>.json`` (both
atomically) under the task's sequence directory, and appends one line per call to
``calls.log`` so tests can count how often each target ran. Config switches make chosen frames
fail (``fail_frames``), produce a non-finite value (``nan_frames``, raising FloatingPointError
like a diverging optimisation), report a missing output (``lie_frames``), ask to be skipped
(``skip_frames``), sleep (``sleep_s``) or kill their worker process (``die_frames``, after
``die_delay_s``).
"""

from __future__ import annotations

import io
import json
import math
import os
import time

import numpy as np

from vsrd_mi.batch import TargetResult, TargetTask, atomic_write_bytes, atomic_write_json

CALLS_LOG = "calls.log"


def samples_for(task: TargetTask) -> np.ndarray:
    """The job's random draw (the reference computation tests compare against)."""
    rng = np.random.default_rng([int(task.seed), int(task.frame)])
    return rng.normal(size=int(task.config.get("n", 256)))


def stats_path(frame: int) -> str:
    return f"stats/{frame:010d}.json"


def samples_path(frame: int) -> str:
    return f"samples/{frame:010d}.npy"


def digest_job(task: TargetTask) -> TargetResult:
    cfg = task.config
    seq_dir = task.sequence_dir
    seq_dir.mkdir(parents=True, exist_ok=True)
    with open(seq_dir / CALLS_LOG, "a", encoding="utf-8") as log:
        log.write(f"{task.frame}\n")
    time.sleep(float(cfg.get("sleep_s", 0.0)))
    if task.frame in cfg.get("die_frames", ()):
        time.sleep(float(cfg.get("die_delay_s", 0.0)))
        os._exit(3)
    if task.frame in cfg.get("fail_frames", ()):
        raise RuntimeError(f"synthetic failure at frame {task.frame}")
    if task.frame in cfg.get("skip_frames", ()):
        return TargetResult(status="skipped")
    samples = samples_for(task)
    if task.frame in cfg.get("nan_frames", ()):
        samples[0] = np.nan
    mean = float(samples.mean())
    if not math.isfinite(mean):
        raise FloatingPointError(f"non-finite loss at frame {task.frame}")
    stats = {"frame": task.frame, "seed": task.seed, "mean": mean, "std": float(samples.std()),
             "n": int(samples.size)}
    buf = io.BytesIO()
    np.save(buf, samples)
    atomic_write_bytes(seq_dir / samples_path(task.frame), buf.getvalue())
    atomic_write_json(seq_dir / stats_path(task.frame), stats)
    outputs = [stats_path(task.frame), samples_path(task.frame)]
    if task.frame in cfg.get("lie_frames", ()):
        outputs.append(f"stats/{task.frame:010d}.missing.json")
    return TargetResult(status="done", outputs=tuple(outputs))


def read_stats(seq_dir, frame: int) -> dict:
    """Parse one stats output (raises on a corrupt file)."""
    return json.loads((seq_dir / stats_path(frame)).read_text(encoding="utf-8"))
