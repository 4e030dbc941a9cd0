"""Scenario presets and two disjoint seed sets: a development set (tune on it) and a validation set
(report only).

Every preset turns on the harder world: vehicles of all procedural classes and the mesh files
drawn in turn (:class:`~vsrd_mi.synth.vehicles.VehicleDeck`), parked rows in parallel, angled and
perpendicular bays facing either way, props in front of the cars, cars out to 60 m beyond the
ego's last position, and a camera pitch and roll drawn per sequence. The presets differ in what
they stress (:data:`SCENARIOS`).

A set is written as ONE KITTI-360 root (shared calibration) holding one or more *rounds*: one
sequence per preset, each with a seed of its own. Round ``r``'s ``i``-th preset is sequence
:data:`SET_SEQUENCE_BASE` + :data:`ROUND_STRIDE` * ``r`` + ``i``, so ``vsrd-mi autolabel ROOT
--sequence N`` and ``vsrd-mi eval --gt ROOT --sequence N`` take its sequences directly. The
validation set has three rounds: a class's size bias is a mean over the few cars of that class a
street holds, and over one round's 3-7 cars its 95 % interval spanned up to 20 points, wider than
the 5 % bound it is held to (docs/evaluation.md). The ``long`` preset (200 frames, for a
whole-sequence throughput figure) belongs to the development and validation sets but is written
only when asked for by name.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

from ..data.kitti360 import sequence_name
from ..errors import DataError
from .attributes import attributes_path
from .cars import bundled_mesh_paths
from .config import ParkingConfig, PropConfig, SynthConfig
from .generate import generate_sequence
from .vehicles import ALL_MESHES, VEHICLE_CLASSES

#: Sequence number of a set's first preset (see the module docstring for the others).
SET_SEQUENCE_BASE = {"development": 100, "validation": 200, "development-traffic": 110}
#: Sequence numbers from one round of a set to the next (a round holds at most
#: :data:`LONG_OFFSET` presets).
ROUND_STRIDE = 10
#: Sequence number offset of the ``long`` preset within its set (in the first round's block).
LONG_OFFSET = 9
#: Seeds of each set: per round, one per preset of :data:`SET_SCENARIOS` in order. No two sets
#: share a seed, and the validation set's later rounds were added after its first round had been
#: reported (docs/accuracy.md), with seeds no run had used.
SET_SEEDS = {"development": ((1301, 1302, 1303, 1304, 1305, 1306),),
             "validation": ((7741, 7742, 7743, 7744, 7745, 7746),
                            (7751, 7752, 7753, 7754, 7755, 7756),
                            (7761, 7762, 7763, 7764, 7765, 7766)),
             "development-traffic": ((1311, 1312, 1313, 1314),)}
#: Seed of each set's ``long`` preset (sets without one have none).
LONG_SEEDS = {"development": 1309, "validation": 7749}

#: Every procedural class once and every mesh file once per deck.
EVEN_MIX: tuple[tuple[str, int], ...] = tuple((c.name, 1) for c in VEHICLE_CLASSES) + \
    ((ALL_MESHES, 1),)
#: Wide and tall vehicles (SUVs, pickups, vans) twice as often as the rest.
WIDE_TALL_MIX: tuple[tuple[str, int], ...] = tuple(
    (c.name, 2 if c.name in ("suv", "pickup", "van") else 1) for c in VEHICLE_CLASSES) + \
    ((ALL_MESHES, 1),)

#: Props per 100 m of street and side: a usual street and a crowded one.
STREET_PROPS = (("pole", 2.5), ("sign", 1.5), ("tree", 3.0), ("pedestrian", 4.0), ("bin", 1.5))
CROWDED_PROPS = (("pole", 4.0), ("sign", 2.5), ("tree", 4.0), ("pedestrian", 10.0), ("bin", 3.0))

#: Camera pitch and roll ranges (degrees) of the presets, around KITTI-360's left camera.
CAMERA_PITCH_DEG = (5.0, 7.0)
CAMERA_ROLL_DEG = (-1.8, 0.6)
#: PNG compression of the suites' images: level 6 writes 7x faster than 9, 4 % larger.
SUITE_PNG_COMPRESSION = 6


@dataclass(frozen=True)
class Scenario:
    """A preset sequence: its length, car counts and configuration."""

    name: str
    description: str
    frames: int
    #: Most parked cars kept (rows are filled, then cut to this many nearest the start).
    n_static: int
    n_dynamic: int
    config: SynthConfig


def hard_config(parking: ParkingConfig = ParkingConfig(),
                props: tuple[tuple[str, float], ...] = STREET_PROPS,
                mix: tuple[tuple[str, int], ...] = EVEN_MIX,
                speed: tuple[float, float] | None = None) -> SynthConfig:
    """The configuration shared by the presets, with the given parking, props and vehicle mix."""
    base = SynthConfig()
    traffic = replace(base.traffic, parking="rows", vehicle_mix=mix,
                      speed=base.traffic.speed if speed is None else speed)
    return replace(base, traffic=traffic, parking=parking,
                   props=replace(PropConfig(), density=props),
                   rig=replace(base.rig, camera_pitch_deg=CAMERA_PITCH_DEG,
                               camera_roll_deg=CAMERA_ROLL_DEG),
                   png_compression=SUITE_PNG_COMPRESSION)


def _scenarios() -> tuple[Scenario, ...]:
    rows = ParkingConfig()
    return (
        Scenario("parked_mixed", "parked-heavy street: all classes, parallel either way round "
                 "(half reversed), some angled and perpendicular bays", 48, 40, 2,
                 hard_config(replace(rows, layouts=(("parallel", 0.6), ("angled", 0.25),
                                                    ("perpendicular", 0.15)),
                                     parallel_reverse_prob=0.5))),
        Scenario("angled_bays", "angled bays 15-60 deg leaning either way, nose or tail to the "
                 "kerb, beside parallel rows", 44, 40, 2,
                 hard_config(replace(rows, layouts=(("angled", 0.7), ("parallel", 0.3)),
                                     bay_reverse_prob=0.4))),
        Scenario("perpendicular_bays", "perpendicular bays, some angled ones, long vehicles "
                 "reaching into the lane", 44, 40, 2,
                 hard_config(replace(rows, layouts=(("perpendicular", 0.6), ("angled", 0.2),
                                                    ("parallel", 0.2))))),
        Scenario("tight_rows", "tight rows (0.5-0.9 m gaps, few holes) behind a crowded "
                 "sidewalk: heavy occlusion, cars out to 60 m", 48, 45, 2,
                 hard_config(replace(rows, gap=(0.5, 0.9), hole_prob=0.05),
                             props=CROWDED_PROPS)),
        Scenario("moving_traffic", "seven moving cars in both lanes past sparser parked rows",
                 48, 30, 7,
                 hard_config(replace(rows, hole_prob=0.3), speed=(2.0, 14.0))),
        Scenario("wide_tall", "SUVs, pickups and vans twice as often, parallel either way and "
                 "perpendicular", 44, 40, 2,
                 hard_config(replace(rows, layouts=(("parallel", 0.6), ("perpendicular", 0.4)),
                                     parallel_reverse_prob=0.5), mix=WIDE_TALL_MIX)),
    )


#: The presets of each set, in sequence-number order.
SCENARIOS: tuple[Scenario, ...] = _scenarios()
#: More development streets with moving traffic: the development and validation sets hold one
#: each (about eight moving cars per set), too few to tune moving cars on. Development only: the
#: validation set stays as it is, so its figures remain comparable.
TRAFFIC_SCENARIOS: tuple[Scenario, ...] = tuple(s for s in SCENARIOS if s.name == "moving_traffic") * 4
#: The presets of each set (a set's seeds pair with them in order).
SET_SCENARIOS = {"development": SCENARIOS, "validation": SCENARIOS,
                 "development-traffic": TRAFFIC_SCENARIOS}
#: The 200-frame preset for a whole-sequence throughput figure (not written by default).
LONG = Scenario("long", "200 frames of a parked-heavy street with moving traffic (throughput)",
                200, 160, 4, hard_config(replace(ParkingConfig(), parallel_reverse_prob=0.5,
                                                 extent=(0.0, 40.0))))


@dataclass(frozen=True)
class SuiteMember:
    """One sequence of a set: a preset, its seed and its sequence number."""

    scenario: Scenario
    seed: int
    sequence: int
    #: Written by default (every preset but ``long``).
    default: bool
    #: The round of its set the member belongs to (0 for ``long``).
    round: int = 0

    def fingerprint(self, mesh_names: tuple[str, ...] = ()) -> str:
        """A hash of everything that decides the sequence's content (preset, seed, number and
        the mesh files' names); the generator's code is not part of it."""
        s = self.scenario
        text = repr((s.name, s.frames, s.n_static, s.n_dynamic, s.config, self.seed,
                     self.sequence, mesh_names))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def suite(name: str) -> list[SuiteMember]:
    """The members of set ``name`` (a key of :data:`SET_SEEDS`), round by round; the development
    and validation sets end with ``long``."""
    if name not in SET_SEEDS:
        raise ValueError(f"unknown set {name!r} (known: {', '.join(SET_SEEDS)})")
    base, scenarios = SET_SEQUENCE_BASE[name], SET_SCENARIOS[name]
    if len(scenarios) > LONG_OFFSET:
        raise ValueError(f"set {name!r}: {len(scenarios)} presets do not fit a round of {LONG_OFFSET}")
    members = []
    for r, seeds in enumerate(SET_SEEDS[name]):
        if len(seeds) != len(scenarios):
            raise ValueError(f"set {name!r} round {r}: {len(seeds)} seeds for {len(scenarios)} presets")
        members += [SuiteMember(s, seed, base + ROUND_STRIDE * r + k, True, r)
                    for k, (s, seed) in enumerate(zip(scenarios, seeds))]
    if name in LONG_SEEDS:
        members.append(SuiteMember(LONG, LONG_SEEDS[name], base + LONG_OFFSET, False))
    return members


def select(members: list[SuiteMember], only: str | None, rounds: int | None = None
           ) -> list[SuiteMember]:
    """The default members (of the first ``rounds`` rounds; None: all), or the one preset called
    ``only`` (``long`` included; every round's)."""
    if rounds is not None and rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    in_rounds = [m for m in members if rounds is None or m.round < rounds]
    if only is None:
        return [m for m in in_rounds if m.default]
    chosen = [m for m in in_rounds if m.scenario.name == only]
    if not chosen:
        raise ValueError(f"no preset {only!r} (known: "
                         f"{', '.join(m.scenario.name for m in members)})")
    return chosen


#: Name of a written set's manifest under its root.
MANIFEST = "suite.json"


def read_manifest(root: Path) -> dict:
    """The manifest of a written set (an empty one when there is none yet)."""
    path = root / MANIFEST
    if not path.is_file():
        return {"format": SUITE_FORMAT, "sequences": {}}
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(path, f"cannot read the suite manifest: {exc}") from exc
    if doc.get("format") != SUITE_FORMAT or not isinstance(doc.get("sequences"), dict):
        raise DataError(path, f"not a {SUITE_FORMAT!r} manifest")
    return doc


#: The ``format`` string of a suite manifest.
SUITE_FORMAT = "vsrd-mi synth suite 1"


def write_suite(root: str | Path, set_name: str, only: str | None = None, force: bool = False,
                meshes: Sequence[str | Path] | None = None,
                progress: Callable[[SuiteMember, int, int], None] | None = None,
                rounds: int | None = None) -> list[tuple[SuiteMember, float | None]]:
    """Write the members of a set (:func:`select`'s of ``only`` and ``rounds``) under ``root``
    (one KITTI-360 root) and its manifest.

    A member whose manifest entry has the same fingerprint and whose files are complete is kept
    (``force`` writes it again). Returns each member with the seconds it took (None: kept).
    """
    root = Path(root)
    mesh_paths = [Path(p) for p in (bundled_mesh_paths() if meshes is None else meshes)]
    mesh_names = tuple(p.name for p in mesh_paths)
    manifest = read_manifest(root)
    out = []
    for member in select(suite(set_name), only, rounds):
        s, key = member.scenario, sequence_name(member.sequence)
        fingerprint = member.fingerprint(mesh_names)
        entry = manifest["sequences"].get(key)
        done = attributes_path(root, key).is_file()
        if not force and done and entry and entry.get("fingerprint") == fingerprint:
            out.append((member, None))
            continue
        summary = generate_sequence(
            root, seq=member.sequence, frames=s.frames, n_static=s.n_static,
            n_dynamic=s.n_dynamic, seed=member.seed, meshes=mesh_paths, config=s.config,
            progress=None if progress is None else functools.partial(progress, member))
        cars = summary.world.cars
        manifest["sequences"][key] = {
            "set": set_name, "preset": s.name, "description": s.description,
            "sequence": member.sequence, "seed": member.seed, "frames": s.frames,
            "cars": len(cars), "moving": sum(c.dynamic for c in cars),
            "camera_pitch_roll_deg": summary.world.camera_attitude,
            "fingerprint": fingerprint, "seconds": round(summary.seconds, 1)}
        (root / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        out.append((member, summary.seconds))
    return out


__all__ = ["MANIFEST", "SUITE_FORMAT", "read_manifest", "write_suite", "CAMERA_PITCH_DEG", "CAMERA_ROLL_DEG", "LONG", "LONG_SEEDS", "ROUND_STRIDE", "SCENARIOS", "SET_SCENARIOS", "SET_SEEDS",
           "SET_SEQUENCE_BASE", "TRAFFIC_SCENARIOS", "Scenario", "SuiteMember", "hard_config", "select", "suite"]
