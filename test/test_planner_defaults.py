"""Every planner default is written three times (ParamSpec, the config dataclasses, the shipped
config/peel_planner_node.yaml); they must agree, name by name."""

from __future__ import annotations

from pathlib import Path

import pytest

from peel_msgs_py.params import load_param_file
from peel_planner_node.config import PARAM_SPECS, PlannerConfig
from peel_planner_node.parameters import NODE_NAME, SPECS

CONFIG = Path(__file__).resolve().parents[1] / "config"

SPEC_DEFAULTS = {s.name: s.default for s in SPECS if s.name != "use_sim_time"}
LIBRARY_DEFAULTS = {s.name: s.default for s in PARAM_SPECS}


def planner_sections() -> list[tuple[str, dict]]:
    """The planner's parameters in each config/*.yaml that sets any (by file name)."""
    out = []
    for path in sorted(CONFIG.glob("*.yaml")):
        if f"{NODE_NAME}:" in path.read_text():
            out.append((path.name, load_param_file(path, NODE_NAME)))
    return out


def test_dataclass_defaults_equal_the_param_specs() -> None:
    assert PlannerConfig().to_params() == LIBRARY_DEFAULTS


@pytest.mark.parametrize(("name", "values"), planner_sections())
def test_yaml_values_equal_the_param_specs(name: str, values: dict) -> None:
    differ = {k: (v, SPEC_DEFAULTS.get(k, "<no spec>")) for k, v in values.items()
              if k not in SPEC_DEFAULTS or SPEC_DEFAULTS[k] != v
              or type(SPEC_DEFAULTS[k]) is not type(v)}
    assert differ == {}, f"{name}: (yaml, spec) of each name that differs"


def test_shipped_yaml_sets_every_planner_parameter() -> None:
    """All but ``model.path``, which the launcher / learner sets (empty = the shipped model)."""
    shipped = load_param_file(CONFIG / f"{NODE_NAME}.yaml", NODE_NAME)
    assert set(shipped) == set(SPEC_DEFAULTS) - {"model.path"}
