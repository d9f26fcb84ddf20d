"""Effects drawn as the power study draws them, acting on the plant (docs/residual.md, end to end).

The draws are seeded and inside the study's families; a drawn effect's action is the study's
shape on the sample's state; the module written for ``peel graph --effect`` imports in a fresh
process through the same loader as the simulator node; on the plant, a drawn F_RZ load raises
the measured F_RZ. Seeds here (5, 7) are not the report's.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from peel_experiments.drawn_effects import PLANT_FAMILIES, PlantEffect, draw_plant_effect, write_draws
from peel_residual.inject import SHAPE_RANGES, shape_of
from peel_sim_node.config import load_sim_config
from peel_sim_node.effects import EffectState
from peel_sim_node.env import PeelEnv


def test_draws_are_seeded_and_only_of_state_functions() -> None:
    draws = [draw_plant_effect(5, i) for i in range(40)]
    assert draws == [draw_plant_effect(5, i) for i in range(40)]
    assert {d.family for d in draws} <= set(PLANT_FAMILIES)
    assert len({d.family for d in draws}) >= 5
    assert "hysteresis" not in PLANT_FAMILIES and "cross_talk" not in PLANT_FAMILIES
    for d in draws:
        assert abs(d.amplitude_n) in (1.0, 2.0) and d.channel in ("fx", "fz")
        for k, (lo, hi) in SHAPE_RANGES[d.family].items():
            assert lo <= d.shape[k] <= hi


@pytest.mark.parametrize("channel", ["fx", "fz"])
def test_the_action_is_the_study_shape_on_the_state(channel: str) -> None:
    e = PlantEffect("periodic_adhesion", channel, -1.5, {"lambda_mm": 5.0, "phase_rad": 0.3})
    s = EffectState(t_s=3.0, q_mm=7.2, v_mmps=2.0, u_mmps=2.0, fx_n=10.0, fz_n=9.0)
    g = -1.5 * np.sin(2 * np.pi * 7.2 / 5.0 + 0.3)
    assert g == pytest.approx(-1.5 * float(shape_of("periodic_adhesion", e.shape, v=[2.0],
                                                    q=[7.2], t=[3.0])[0]))
    a = e(s)
    assert (a.load_n, a.resist_n) == pytest.approx((g, 0.0) if channel == "fz" else (0.0, g))
    with pytest.raises(ValueError, match=r"hysteresis.*cannot act on the plant"):
        PlantEffect("hysteresis", "fz", 1.0, {"dv0_mmps": 0.3})


def test_the_written_module_loads_as_the_simulator_node_loads_it(tmp_path: Path) -> None:
    draws = write_draws(7, 2, tmp_path)
    assert json.loads((tmp_path / "draws.json").read_text()) == draws
    code = ("import json, sys; from peel_sim_node.effects import load_effect; "
            "e = load_effect(sys.argv[1]); print(json.dumps(e.to_json()))")
    for d in draws:
        env = {"PYTHONPATH": f"{tmp_path}:{':'.join(sys.path)}"}
        out = subprocess.run([sys.executable, "-c", code, f"{d['module']}:effect"], env=env,
                             capture_output=True, text=True, check=True, timeout=120)
        assert json.loads(out.stdout) == {k: d[k] for k in ("family", "channel", "amplitude_n",
                                                             "shape")}
    bad = subprocess.run([sys.executable, "-m", "peel_experiments.drawn_effects", "--seed", "7",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().endswith("drawn_effect_0.py exists (give --force to replace it)")
    assert len(bad.stderr.strip().splitlines()) == 1


def test_a_drawn_load_raises_the_measured_force_on_the_plant() -> None:
    cfg = load_sim_config()
    load = PlantEffect("sensor_offset", "fz", 2.0)

    def run(effects: list) -> np.ndarray:
        with PeelEnv(cfg, seed=5, source="plant", level=0, effects=effects) as env:
            env.reset(seed=5)
            for _ in range(40):
                if env.done:
                    break
                env.step(1.5)
            return env.history.fz

    base, more = run([]), run([load])
    n = min(len(base), len(more))
    # the blade sinks deeper into the pad under the extra load, so F_RZ rises by less than 2 N
    assert 0.5 < float(np.mean(more[10:n] - base[10:n])) < 2.5
