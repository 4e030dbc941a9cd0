"""The adaptive sampler of this working tree against the one at an earlier git revision, side by side in one process: forward + backward step time on the integrator benchmark's scenes.

The ratio of adaptive to dense moves more between runs on a noisy machine than a change to the
sampler moves it, so a change is measured here against the sampler it replaces, timed in turn
in one loop (median of ``--steps`` steps each, after two warm-up steps). The earlier
``plugins/silhouette.py`` is read from ``git show REV:plugins/silhouette.py`` and loaded as a
module of the current ``vsrd_plugins`` package, so it runs on the current ``sdf`` module: the
revision's integrator must work with it (true while ``sdf`` only gains functions). Both load
the same options (``vsrd_mi.bench.integrator.integrator_description``) on the same rays; the
labels of the two are compared as well.

Usage::

    python benchmarks/sampler_vs_revision.py --rev 36e9707 --out benchmarks/sampler_vs_revision.json
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from common import side_by_side_steps, write_results
import vsrd_mi  # noqa: F401  (sets the variant, registers the plugins)
import vsrd_plugins
from vsrd_mi.bench import integrator as bench

#: (instances, rays) cases timed by default: the issue's target case, more boxes, the product's rays.
CASES = ((6, 16384), (12, 16384), (6, 1024))
REPO = Path(__file__).resolve().parent.parent


def revision_module(rev: str, folder: Path):
    """``plugins/silhouette.py`` at ``rev`` as the module ``vsrd_plugins._silhouette_at_rev``."""
    source = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:plugins/silhouette.py"],
                            check=True, capture_output=True, text=True).stdout
    path = folder / "silhouette_at_rev.py"
    path.write_text(source)
    name = f"{vsrd_plugins.__name__}._silhouette_at_rev"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def integrator_from(cls, description: dict):
    """An integrator of class ``cls`` from a ``mi.load_dict`` description."""
    props = mi.Properties()
    for key, value in description.items():
        if key not in ("type", "id"):
            props[key] = value
    return cls(props)


def run_case(old_cls, n_inst: int, n_rays: int, steps: int, cfg: bench.BenchConfig) -> dict:
    data, _ = bench.case_data(cfg, n_inst, True)
    batch = data.batch(n_rays)
    description = bench.integrator_description(data.boxes, "adaptive", True, cfg)
    runs = {"revision": bench.TimedIntegrator(integrator_from(old_cls, description), batch, cfg, 1),
            "working tree": bench.TimedIntegrator(mi.load_dict(description), batch, cfg, 1)}
    labels = {}
    for name, run in runs.items():
        with dr.suspend_grad():
            labels[name] = np.stack([np.array(x) for x in run.it.render_rays(batch.o, batch.d, batch.time)])
    times = side_by_side_steps(runs, steps)
    median = {name: float(np.median(t)) for name, t in times.items()}
    return {"instances": n_inst, "rays": n_rays, "median_s": median, "steps_s": times,
            "speedup": median["revision"] / median["working tree"],
            "labels_max_abs_diff": float(np.abs(labels["revision"] - labels["working tree"]).max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rev", required=True, help="git revision of the earlier sampler")
    parser.add_argument("--steps", type=int, default=9, help="timed steps per sampler and case")
    parser.add_argument("--cases", default=",".join(f"{k}x{n}" for k, n in CASES),
                        help="instances x rays per case, comma-separated (default: %(default)s)")
    parser.add_argument("--out", type=Path, help="write the results as JSON here")
    args = parser.parse_args()
    start = time.perf_counter()
    cfg = bench.BenchConfig()
    with tempfile.TemporaryDirectory() as tmp:
        old_cls = revision_module(args.rev, Path(tmp)).VSRDSilhouetteIntegrator
        cases = []
        for n_inst, n_rays in (map(int, c.split("x")) for c in args.cases.split(",")):
            case = run_case(old_cls, n_inst, n_rays, args.steps, cfg)
            cases.append(case)
            m = case["median_s"]
            print(f"{n_inst:2d} boxes {n_rays:6d} rays: revision {m['revision']:.3f} s, working tree "
                  f"{m['working tree']:.3f} s, {case['speedup']:.2f}x; labels differ by up to "
                  f"{case['labels_max_abs_diff']:.1e}", flush=True)
    rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", args.rev], check=True, capture_output=True,
                         text=True).stdout.strip()
    if args.out:
        write_results(args.out, __doc__, time.perf_counter() - start, revision=rev,
                      head=bench.git_commit(), cases=cases)


if __name__ == "__main__":
    main()
