"""One side of ``vsrd-mi bench autolabel``: autolabel target frames with the code on ``sys.path``.

Run as a script, ``python -P autolabel_worker.py JOB.json``, with ``PYTHONPATH`` pointing at the
tree to measure (this checkout, or an export of another git revision). At start it imports only
the standard library; the package is imported when the job runs, from whichever tree is on the
path, and the per-target job and the consensus are looked up under the module names the
revisions since ed219dd used (:data:`JOB_MODULES`, :data:`CONSENSUS_MODULES`). So one worker
measures the code of any of those revisions the same way.

The job (JSON) names the configuration (a preset of the revision plus ``--set`` style overrides,
built by that revision's own ``AutolabelConfig``), the sequences with their target frames, an
output directory per sequence and whether to record Dr.Jit's kernel history. Per target it
records the wall time, the time of each phase (observations, stereo initialisation, scene
set-up, optimisation, the rest), the steps run and, with the kernel history on, the kernels
launched per step and those that were not in the in-memory kernel cache (loaded from disk or
compiled) in the first :data:`WARMUP_STEPS` steps and after them. After each sequence's targets it
runs the sequence-level consensus, as ``vsrd-mi autolabel`` does. The result (JSON) also holds
the process's peak resident memory.
"""

from __future__ import annotations

import importlib
import json
import resource
import sys
import time
from pathlib import Path

#: Modules holding ``process_target`` (the per-target job), newest layout first.
JOB_MODULES = ("vsrd_mi.autolabel.job", "vsrd_mi.optimise.autolabel")
#: Modules holding ``apply_consensus`` (the consensus of parked cars), newest layout first.
CONSENSUS_MODULES = ("vsrd_mi.autolabel.consensus", "vsrd_mi.optimise.consensus")
#: Steps at the start of each target whose new kernels count as warm-up: a target's first steps
#: build kernels for its number of boxes and its sample layouts; after them none should be new.
WARMUP_STEPS = 10


def first_module(names: tuple[str, ...]):
    """The first of ``names`` that imports (the layout of the revision on the path)."""
    for name in names:
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is None or not name.startswith(exc.name):
                raise  # a module that exists but fails to import is an error, not another layout
    raise ModuleNotFoundError(f"none of {names} on {sys.path}")


def only_the_path() -> None:
    """Drop the import finders of editable installs (setuptools' ``__editable__`` modules): they
    come after the path in ``sys.meta_path`` and would complete a revision's package with the
    modules it lacks from the installed checkout (``vsrd_mi.autolabel`` from main in a tree of a
    revision without it)."""
    sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable__")]


def foreign_modules(package: str) -> list[str]:
    """Loaded modules of ``package`` whose file lies outside the package's folder (should be none)."""
    root = Path(sys.modules[package].__file__).parent
    return [name for name, m in list(sys.modules.items())
            if (name == package or name.startswith(package + ".")) and getattr(m, "__file__", None)
            and root not in Path(m.__file__).parents]


def peak_rss_mib() -> float:
    """Peak resident set size of this process (MiB; Linux reports ``ru_maxrss`` in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class Phases:
    """Wall time per named phase of the current target, measured by wrapping functions."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start
        timed.__wrapped__ = fn
        return timed


class KernelSteps:
    """Kernels per optimisation step from Dr.Jit's kernel history (read and cleared each step):
    every launch (JIT kernels, memsets, reductions, ...), and the JIT kernels new to the process
    (loaded from the disk cache or compiled) and compiled."""

    def __init__(self, dr) -> None:
        self.dr = dr
        self.launched: list[int] = []
        self.new: list[int] = []
        self.compiled: list[int] = []
        dr.kernel_history()  # drop what ran before the first step

    def step(self) -> None:
        history = self.dr.kernel_history()
        jit = [k for k in history if k["type"] == self.dr.KernelType.JIT]
        self.launched.append(len(history))
        # a JIT kernel's cache_hit: found in the in-memory or the disk cache; cache_disk: the disk's
        self.new.append(sum(1 for k in jit if k.get("cache_disk") or not k.get("cache_hit")))
        self.compiled.append(sum(1 for k in jit if not k.get("cache_hit")))

    def summary(self) -> dict:
        w = WARMUP_STEPS
        after = self.launched[w:]
        return {
            "launched_per_step": sum(after) / len(after) if after else None,
            "new_in_warmup": sum(self.new[:w]), "compiled_in_warmup": sum(self.compiled[:w]),
            "new_after_warmup": sum(self.new[w:]), "compiled_after_warmup": sum(self.compiled[w:]),
            "steps_with_new_kernels": [i for i, n in enumerate(self.new) if n and i >= w][:20],
        }


def instrument(job_module, phases: Phases, kernel_history: bool) -> dict:
    """Wrap the revision's phase functions (module attributes, so that late imports see them
    too) and the optimiser's ``run``; returns the per-target record being filled."""
    import drjit as dr

    record: dict = {}
    optimiser_module = importlib.import_module("vsrd_mi.optimise.optimiser")
    init_module = importlib.import_module("vsrd_mi.init.sequence")
    for module, name, phase in ((job_module, "load_observations", "observations"),
                                (init_module, "initialise_target", "initialisation"),
                                (job_module, "initialise_target", "initialisation")):
        if hasattr(module, name):
            setattr(module, name, phases.wrap(phase, getattr(module, name)))
    cls = optimiser_module.BoxOptimiser
    cls.__init__ = phases.wrap("scene", cls.__init__)
    run = cls.run

    def instrumented_run(self, progress=None):
        steps = KernelSteps(dr) if kernel_history else None

        def each_step(step, loss):
            if steps is not None:
                steps.step()
            if progress is not None:
                progress(step, loss)
        result = phases.wrap("optimisation", run)(self, each_step)
        record["steps"] = int(result.steps)
        record["stopped_early"] = bool(result.stopped_early)
        if steps is not None:
            record["kernels"] = steps.summary()
        return result

    cls.run = instrumented_run
    if kernel_history:
        dr.set_flag(dr.JitFlag.KernelHistory, True)
    return record


def run_job(job: dict) -> dict:
    """Autolabel every sequence's targets of ``job`` (see the module docstring)."""
    start = time.perf_counter()
    vsrd_mi = importlib.import_module("vsrd_mi")
    job_module = first_module(JOB_MODULES)
    consensus_module = first_module(CONSENSUS_MODULES)
    tasks_module = importlib.import_module("vsrd_mi.batch.tasks")
    config_module = importlib.import_module("vsrd_mi.optimise.config")
    kitti = importlib.import_module("vsrd_mi.data.kitti360")
    import_seconds = time.perf_counter() - start
    cfg = config_module.PRESETS[job["preset"]]().with_overrides(list(job["overrides"]))
    phases = Phases()
    record = instrument(job_module, phases, bool(job["kernel_history"]))
    sequences = []
    for item in job["sequences"]:
        seq = kitti.Sequence(item["root"], item["sequence"])
        rows = []
        for frame in item["targets"]:
            phases.seconds.clear()
            record.clear()
            task = tasks_module.TargetTask(root=item["root"], sequence=seq.name, frame=int(frame),
                                           output_dir=item["out_dir"], config=cfg.to_dict(),
                                           seed=int(job["seed"]))
            t = time.perf_counter()
            try:
                result = job_module.process_target(task)
                status, error = result.status, result.error
            except Exception as exc:  # recorded; the other targets go on
                status, error = "failed", f"{type(exc).__name__}: {exc}"
            seconds = time.perf_counter() - t
            phase_seconds = dict(phases.seconds)
            phase_seconds["rest"] = seconds - sum(phase_seconds.values())
            rows.append({"frame": int(frame), "status": status, "error": error, "seconds": seconds,
                         "phases": phase_seconds, "rss_mib_peak": peak_rss_mib(), **record})
            print(f"  {vsrd_mi.__file__.rsplit('/', 2)[0]} {seq.name} target {frame}: {status} "
                  f"{seconds:.1f} s, {record.get('steps')} steps", flush=True)
        t = time.perf_counter()
        try:
            args = [Path(item["out_dir"]) / seq.name, seq, cfg.consensus]
            if hasattr(cfg, "heading"):
                args.append(cfg.heading)
            consensus_module.apply_consensus(*args)
            consensus_error = None
        except Exception as exc:  # recorded; the targets' own labels are scored
            consensus_error = f"{type(exc).__name__}: {exc}"
        sequences.append({"name": item["name"], "root": item["root"], "sequence": seq.name, "targets": rows,
                          "consensus_seconds": time.perf_counter() - t, "consensus_error": consensus_error})
    return {"package": vsrd_mi.__file__, "import_seconds": import_seconds, "sequences": sequences,
            "config": cfg.to_dict(), "peak_rss_mib": peak_rss_mib()}


def run_cli(job: dict) -> dict:
    """``vsrd-mi ARGS`` of the revision on the path, in this process: exit code, wall time, peak memory."""
    cli = importlib.import_module("vsrd_mi.cli")
    start = time.perf_counter()
    code = cli.main(list(job["cli"]))
    return {"exit_code": int(code), "seconds": time.perf_counter() - start, "peak_rss_mib": peak_rss_mib()}


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print("usage: python -P autolabel_worker.py JOB.json RESULT.json", file=sys.stderr)
        return 2
    job = json.loads(Path(argv[1]).read_text())
    only_the_path()
    result = run_cli(job) if "cli" in job else run_job(job)
    foreign = foreign_modules("vsrd_mi")
    if foreign:
        raise RuntimeError(f"modules imported from outside {sys.modules['vsrd_mi'].__file__}: {foreign}")
    Path(argv[2]).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
