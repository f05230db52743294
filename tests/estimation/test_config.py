"""ReconstructionConfig: a value out of range, or a field it does not have, is refused with the field's full
name (what the CLI and the REST service show the user)."""

import pydantic
import pytest

from estimation.config import ReconstructionConfig


@pytest.mark.parametrize(("section", "field", "value"), [
    ("mapper", "refinement_relative_error_tol", 0.0),
    ("mapper", "final_min_change", -0.1),
    ("mapper", "growth_refinement_rounds", 0),
    ("mapper", "pnp_threshold_noise_factor", -1.0),
    ("mapper", "relaxed_registration_factor", 1.5),
    ("mapper", "refinement_max_iterations", 0),
    ("mapper", "initial_pair_max_error_px", 0.0),
    ("mapper", "verify_max_rotation_std_deg", 0.0),
    ("mapper", "verify_veto_support_ratio", 1.5),
    ("mapper", "registration_turn_deg", -10.0),
    ("mapper", "registration_turn_min_gain", 1.0),
    ("mapper", "local_intrinsics_until_images", 1),
    ("mapper", "fold_min_shared", 1.5),
    ("mapper", "fold_max_angle_deg", 0.0),
    ("mapper", "fold_min_pairs", 0),
    ("mapper", "merge_min_overlap", 0.0),
    ("two_view", "max_rotation_residual_deg", 200.0),
    ("two_view", "anchor_pairs_per_image", 0),
    ("bundle_adjustment", "local_max_iterations", 0),
    ("bundle_adjustment", "local_max_iterations_refining", 0),
])
def test_an_out_of_range_mapper_ba_or_pair_setting_is_refused_naming_its_field(section, field, value):
    with pytest.raises(pydantic.ValidationError) as refused:
        ReconstructionConfig(**{section: {field: value}})
    assert [error["loc"] for error in refused.value.errors()] == [(section, field)]


@pytest.mark.parametrize(("field", "value"), [
    ("optimizer", "dogleg"),
    ("mapper_optimizer", "newton"),
    ("mapper_refining_optimizer", "dogleg"),
    ("mapper_global_ordering", "amd"),
    ("mapper_refining_global_ordering", "colamd_fast"),
])
def test_an_unknown_optimizer_or_ordering_of_the_bundle_adjustment_is_refused_naming_its_field(field, value):
    with pytest.raises(pydantic.ValidationError) as refused:
        ReconstructionConfig(bundle_adjustment={field: value})
    assert [error["loc"] for error in refused.value.errors()] == [("bundle_adjustment", field)]


def test_sift_device_accepts_only_auto_cpu_or_cuda():
    with pytest.raises(pydantic.ValidationError) as refused:
        ReconstructionConfig(sift={"device": "mps"})
    assert [error["loc"] for error in refused.value.errors()] == [("sift", "device")]


@pytest.mark.parametrize(("settings", "location"), [
    ({"mapper": {"min_pnp_inlier": 5}}, ("mapper", "min_pnp_inlier")),          # min_pnp_inliers misspelt
    ({"bundle_adjustment": {"huber_px": 1.0}}, ("bundle_adjustment", "huber_px")),
    ({"two_view": {"min_inliers": 15, "ratio": 0.8}}, ("two_view", "ratio")),   # a SiftConfig field
    ({"siftt": {}}, ("siftt",)),
])
def test_an_unknown_setting_is_refused_naming_it_instead_of_being_ignored(settings, location):
    with pytest.raises(pydantic.ValidationError) as refused:
        ReconstructionConfig.model_validate(settings)
    errors = refused.value.errors()
    assert [(error["loc"], error["type"]) for error in errors] == [(location, "extra_forbidden")]
