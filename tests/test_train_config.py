import json

import pytest

from gear.config import TrainConfig, load_config, load_overrides, make_config


def test_table_s1_defaults():
    c = TrainConfig()
    assert (c.stage3_iterations, c.em_interval, c.knn_neighbors) == (30_000, 500, 3)
    assert (c.joint_classify_iteration, c.revolute_eps_deg) == (10_000, 10.0)
    assert (c.lambda_dssim, c.lambda_depth, c.lambda_sam, c.lambda_knn) == (0.2, 1.0, 0.1, 0.1)
    assert (c.gamma_prism, c.small_part_threshold, c.dilation_radius) == (4.0, 2000, 1)
    assert c.densify_grad_threshold == 2e-4 and c.opacity_reset_interval == 3000


def test_profiles_change_schedule_not_weights():
    full, fast, quick = (make_config(p) for p in ("full", "fast", "quick"))
    assert (fast.stage1_iterations, fast.stage3_iterations) == (10_000, 10_000)
    assert quick.stage3_iterations < fast.stage3_iterations
    for c in (fast, quick):
        assert (c.lambda_sam, c.lambda_knn, c.gamma_prism) == (
            full.lambda_sam, full.lambda_knn, full.gamma_prism)


def test_json_round_trip(tmp_path):
    c = make_config("quick", {"em_interval": 77, "num_parts": 3, "schedule": "joint"})
    c.save(tmp_path / "config.json")
    assert load_config(tmp_path / "config.json") == c


def test_overrides_reject_unknown_fields_and_bad_values(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"em_intervall": 10}))
    with pytest.raises(ValueError, match="em_intervall"):
        load_overrides(path)
    with pytest.raises(ValueError, match="schedule"):
        make_config("fast", {"schedule": "alternate"})
    with pytest.raises(ValueError, match="em_interval"):
        make_config("fast", {"em_interval": 0})
    with pytest.raises(ValueError, match="not found"):
        load_overrides(tmp_path / "missing.json")


def test_m_step_views_is_a_field_that_round_trips_and_defaults_for_old_configs(tmp_path):
    c = make_config("quick", {"m_step_views": 2})
    c.save(tmp_path / "config.json")
    assert load_config(tmp_path / "config.json").m_step_views == 2
    # A config.json (or checkpoint config) written before the field existed resumes with the
    # default of 4 views per M-step.
    old = json.loads(make_config("quick").to_json())
    del old["m_step_views"]
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert load_config(tmp_path / "old.json").m_step_views == 4
    with pytest.raises(ValueError, match="m_step_views"):
        make_config("quick", {"m_step_views": 0})
