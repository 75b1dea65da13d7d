"""Shipped parameter files and generated docs stay in step with the declared parameters."""
import pytest
import yaml

from conftest import ROOT
from profile_pose_ros.nodes import pose_estimator
from profile_pose_ros.tools.param_docs import generated, node_modules


def test_parameter_reference_is_generated_from_descriptors():
    assert (ROOT / "docs" / "parameters.md").read_text() == generated(), (
        "regenerate: python -m profile_pose_ros.tools.param_docs > docs/parameters.md")


@pytest.mark.parametrize("module", node_modules(), ids=lambda m: m.NODE_NAME)
def test_params_file_names_exactly_the_declared_parameters_within_range(module):
    document = yaml.safe_load((ROOT / "config" / f"{module.NODE_NAME}.yaml").read_text())
    values = document[module.NODE_NAME]["ros__parameters"]
    declared = {p.name: p for p in module.PARAMETERS}
    assert set(values) == set(declared)
    for name, value in values.items():
        p = declared[name]
        assert type(value) is type(p.default), name
        if p.low is not None:
            assert p.low <= value <= p.high, name


def test_pose_estimator_params_file_is_a_valid_combination():
    values = yaml.safe_load((ROOT / "config" / "pose_estimator.yaml").read_text())["pose_estimator"]["ros__parameters"]
    pose_estimator.options_from(values)
