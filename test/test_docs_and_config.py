"""Shipped parameter files and generated docs stay in step with the declared parameters."""
import yaml

from conftest import ROOT
from profile_pose_ros.nodes import pose_estimator
from profile_pose_ros.tools.param_docs import generated


def test_parameter_reference_is_generated_from_descriptors():
    assert (ROOT / "docs" / "pose_estimator_parameters.md").read_text() == generated(), (
        "regenerate: python -m profile_pose_ros.tools.param_docs > docs/pose_estimator_parameters.md")


def test_params_file_names_exactly_the_declared_parameters_within_range():
    document = yaml.safe_load((ROOT / "config" / "pose_estimator.yaml").read_text())
    values = document["pose_estimator"]["ros__parameters"]
    declared = {p.name: p for p in pose_estimator.PARAMETERS}
    assert set(values) == set(declared)
    for name, value in values.items():
        p = declared[name]
        assert type(value) is type(p.default), name
        if p.low is not None:
            assert p.low <= value <= p.high, name
    pose_estimator.options_from(values)  # a valid combination
