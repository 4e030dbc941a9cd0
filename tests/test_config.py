"""Configuration presets and the CLI's ``--set KEY=VALUE`` overrides."""

import dataclasses
import json

import pytest

from vsrd_mi.batch.tasks import TargetTask
from vsrd_mi.init.config import InitConfig
from vsrd_mi.optimise.config import (LONG_SCHEDULE_SHAPE_PRIOR, PAPER_LR_DECAY, PAPER_SILHOUETTE_WEIGHT, AutolabelConfig,
                                     CarProfile, LossWeights, default_config, paper_config)


def test_presets_differ_in_budget_lr_decay_the_silhouette_term_and_the_long_schedules_shape_prior_only():
    d, p = default_config(), paper_config()
    assert (p.steps, p.warmup_steps, p.rays_per_step, p.sampling) == (3000, 1000, 1000, "dense")
    assert not p.early_stop.enabled and d.early_stop.enabled
    assert p.residual and not d.residual
    assert d.weights == LossWeights()
    prior = ("init_size", "init_size_dynamic")
    assert all(getattr(d.weights, k) == 0.0 for k in prior)  # the default runs without the size prior ...
    for k in ("init_yaw", "init_yaw_dynamic"):  # ... with the yaw priors, in both presets
        assert getattr(p.weights, k) == getattr(d.weights, k) > LONG_SCHEDULE_SHAPE_PRIOR
    assert all(getattr(p.weights, k) == LONG_SCHEDULE_SHAPE_PRIOR > 0 for k in prior)
    assert d.weights.silhouette == 0.0 and p.weights.silhouette == PAPER_SILHOUETTE_WEIGHT == 1.0
    # nothing else differs
    assert dataclasses.replace(p.weights, silhouette=0.0, **{k: 0.0 for k in prior}) == d.weights
    assert p.car_profile == d.car_profile == CarProfile() and d.car_profile.enabled
    # the paper decays its rates by 0.01 over 3000 steps; the default's 600 steps decay less
    assert p.lr.decay == PAPER_LR_DECAY == 0.01 < d.lr.decay
    assert dataclasses.replace(p.lr, decay=d.lr.decay) == d.lr


def test_overrides_set_nested_and_top_level_fields():
    cfg = default_config().with_overrides(["weights.init_dynamic=0.1", "lr.box=0.02", "steps=50",
                                           "sampling=dense", "early_stop.enabled=false", "residual=false"])
    assert cfg.weights.init_dynamic == 0.1 and isinstance(cfg.weights.init_dynamic, float)
    assert cfg.lr.box == 0.02 and cfg.steps == 50 and cfg.sampling == "dense"
    assert cfg.early_stop.enabled is False and cfg.residual is False
    # integers given to float fields become floats; the source config is unchanged
    assert default_config().with_overrides(["weights.init=1"]).weights.init == 1.0
    assert default_config().weights.init_dynamic == LossWeights().init_dynamic
    assert AutolabelConfig.from_dict(cfg.to_dict()) == cfg
    # the paper's box corners: a zero car profile, round-tripped through the dict form
    corners = default_config().with_overrides(["car_profile.clearance=0", "car_profile.overhang=0",
                                                 "car_profile.corner=0", "car_profile.mirror=0",
                                                 "car_profile.roof=1"])
    assert not corners.car_profile.enabled and AutolabelConfig.from_dict(corners.to_dict()) == corners


def test_overrides_set_tuple_fields_from_json_lists():
    """A tuple field (e.g. the initialisation's typical car size) takes a JSON list of as many
    numbers; anything else is refused naming the key."""
    cfg = default_config().with_overrides(["stereo_init.footprint.typical_size=[1.7, 1.5, 4]"])
    assert cfg.stereo_init.footprint.typical_size == (1.7, 1.5, 4.0)
    assert AutolabelConfig.from_dict(cfg.to_dict()) == cfg
    for bad in ("[1.7, 1.5]", "[1.7, true, 4]", "1.7"):
        with pytest.raises(ValueError, match="stereo_init.footprint.typical_size"):
            default_config().with_overrides([f"stereo_init.footprint.typical_size={bad}"])


def test_surface_min_quantile_out_of_range_is_refused_naming_it():
    for bad in ("-0.1", "0.5"):
        with pytest.raises(ValueError, match="surface.min_quantile must be in"):
            default_config().with_overrides([f"surface.min_quantile={bad}"])
    assert default_config().with_overrides(["surface.min_quantile=0"]).surface.min_quantile == 0.0
    footprint = default_config().with_overrides(["stereo_init.footprint.min_quantile=0"]).stereo_init.footprint
    assert footprint.min_quantile == 0.0


def test_the_residual_field_needs_the_silhouette_term():
    """The residual field acts only through the rendered silhouettes: switching it on without
    their loss is refused with the fix in the message; with it, it is accepted."""
    with pytest.raises(ValueError, match="residual=true needs weights.silhouette > 0"):
        default_config().with_overrides(["residual=true"])
    cfg = default_config().with_overrides(["residual=true", "weights.silhouette=1"])
    assert cfg.residual and cfg.weights.silhouette == 1.0


def test_the_stereo_initialisation_is_part_of_the_config():
    """Its settings are ``--set`` overridable, survive the JSON round trip the batch tasks make
    (nested groups, tuples) and so change a task's fingerprint."""
    cfg = default_config().with_overrides(["stereo_init.footprint.fit_quantile=0.5",
                                           "stereo_init.agreement_share=0"])
    assert cfg.stereo_init.footprint.fit_quantile == 0.5 and cfg.stereo_init.agreement_share == 0.0
    assert default_config().stereo_init == InitConfig()
    for c in (default_config(), cfg):
        back = AutolabelConfig.from_dict(json.loads(json.dumps(c.to_dict())))
        assert back == c and isinstance(back.stereo_init.footprint.typical_size, tuple)
    task = TargetTask(root="r", sequence="s", frame=3, output_dir="o", config=default_config().to_dict())
    other = dataclasses.replace(task, config=cfg.to_dict())
    assert task.fingerprint() != other.fingerprint()
    with pytest.raises(ValueError, match="stereo_init.footprint.nope"):
        default_config().with_overrides(["stereo_init.footprint.nope=1"])
    with pytest.raises(TypeError):
        InitConfig.from_dict({"footprint": {"nope": 1}})


@pytest.mark.parametrize("item, message", [
    ("weights.nope=1", "unknown field 'nope'"),
    ("nope.init=1", "'nope' is not a configuration group"),
    ("weights=1", "unknown field 'weights'"),
    ("steps=1.5", "is not a valid int value"),
    ("steps=many", "is not a valid int value"),
    ("residual=1", "is not a valid bool value"),
    ("sampling=3", "is not a valid str value"),
    ("weights.init", "expected KEY=VALUE"),
    ("stereo_init.footprint.fit_quantile=1.5", "footprint.fit_quantile must be in"),
    ("stereo_init.footprint.min_quantile=0.5", "footprint.min_quantile must be in"),
    ("stereo_init.footprint.reference_range=0", "footprint.reference_range must be > 0"),
    ("stereo_init.footprint.max_fit_points=0", "footprint.max_fit_points must be >= 1"),
    ("stereo_init.footprint.edge_percentile=60", "footprint.edge_percentile must be in"),
    ("stereo_init.footprint.typical_size=[1.8, 1.5, 7.0]", "footprint.typical_size and footprint.max_size"),
])
def test_bad_overrides_name_the_key(item, message):
    with pytest.raises(ValueError, match=message):
        default_config().with_overrides([item])


@pytest.mark.parametrize("name", ["init_anchor", "init_anchor_dynamic"])
def test_init_anchor_takes_its_two_choices_and_refuses_others_naming_it(name):
    assert getattr(default_config().weights, name) == "seen_faces"
    assert getattr(default_config().with_overrides([f"weights.{name}=centre"]).weights, name) == "centre"
    with pytest.raises(ValueError, match=f"weights.{name} must be one of"):
        default_config().with_overrides([f"weights.{name}=corner"])


@pytest.mark.parametrize("item, message", [("weights.length_prior=-1", "weights.length_prior must be >= 0"),
                                           ("weights.width_prior=-0.5", "weights.width_prior must be >= 0"),
                                           ("weights.length_prior_px=0", "weights.length_prior_px must be > 0")])
def test_size_prior_settings_are_checked_naming_them(item, message):
    with pytest.raises(ValueError, match=message):
        default_config().with_overrides([item])
