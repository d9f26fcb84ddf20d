"""Bad simulator input: clear errors naming the field, exit 2 from the CLI."""

import subprocess
import sys

import numpy as np
import pytest

from peel_msgs_py.errors import PeelError
from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv


@pytest.mark.parametrize("name,value,msg", [
    ("randomization.stiffness_low", -5.0, "randomization.stiffness_low"),
    ("task.q_ter_mm", 0.0, "task.q_ter_mm"),
    ("task.q_ter_mm", -1.0, "task.q_ter_mm"),
    ("randomization.friction_high", float("nan"), "randomization.friction_high"),
    ("randomization.damping_low", 5000.0, "randomization.damping_low"),  # inverted interval
    ("plant.friction_low", 3.0, "plant.friction_low"),  # inverted interval
    ("task.t_max_s", "sixty", "task.t_max_s"),
    ("scene.no_such_thing", 1.0, "scene.no_such_thing"),
])
def test_bad_config_names_the_field(name, value, msg):
    with pytest.raises(PeelError, match=msg.replace(".", r"\.")):
        load_sim_config({name: value})


def test_bad_params_and_commands():
    cfg = load_sim_config()
    with pytest.raises(PeelError, match="stiffness"):
        PeelEnv(cfg, params={"friction": 1.0, "stiffness": -1.0, "damping": 1.0})
    with pytest.raises(PeelError, match="damping"):
        PeelEnv(cfg, params={"friction": 1.0, "stiffness": 1e4})
    with PeelEnv(cfg, seed=0) as env:
        with pytest.raises(PeelError, match="u_mmps"):
            env.step(float("nan"))
        with pytest.raises(PeelError, match="rollout"):
            env.rollout(np.zeros(5))
    with pytest.raises(PeelError, match="source"):
        PeelEnv(cfg, source="real")


def test_cli_bad_params_file_exits_2(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("peel_sim_node:\n  ros__parameters:\n    randomization:\n"
                 "      stiffness_low: -100.0\n")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "dataset", "--out", str(out),
                        "--params-file", str(f)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "randomization.stiffness_low" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()
