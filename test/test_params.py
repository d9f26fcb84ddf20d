"""peel_msgs_py.params.validate_group: one group of a flat ROS 2 parameter dict."""

import pytest

from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import ParamSpec, validate_group

SPECS = [ParamSpec("train.lr", float, 1e-4, min=0.0), ParamSpec("train.epochs", int, 60, min=1)]


def test_group_is_validated_other_groups_ignored_and_prefix_stripped() -> None:
    flat = {"train.lr": 1e-3, "model.h": 10, "trainer.x": "not mine"}
    assert validate_group(SPECS, flat, "train") == {"train.lr": 1e-3, "train.epochs": 60}
    assert validate_group(SPECS, flat, "train", strip=True) == {"lr": 1e-3, "epochs": 60}


def test_bad_value_in_the_group_names_the_parameter() -> None:
    with pytest.raises(ParameterError, match=r"'train\.epochs'"):
        validate_group(SPECS, {"train.epochs": 0}, "train")
    with pytest.raises(ParameterError, match=r"unknown parameter 'train\.lrr'"):
        validate_group(SPECS, {"train.lrr": 1.0}, "train")
