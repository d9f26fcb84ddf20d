"""One task seed and one state sample for every package (peel_msgs_py.task)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from peel_msgs_py import task

SRC = Path(__file__).resolve().parents[1] / "src"


def defined(name: str) -> list[str]:
    """Modules under src/ that define a function or class ``name``."""
    out = []
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text())
        if any(isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name == name
               for n in ast.walk(tree)):
            out.append(str(path.relative_to(SRC)))
    return out


def test_task_seed_and_sample_are_defined_once() -> None:
    assert defined("task_seed") == ["peel_msgs_py/peel_msgs_py/task.py"]
    assert defined("StateSample") == []
    assert [p for p in defined("Sample") if "protocol" not in p] == [
        "peel_msgs_py/peel_msgs_py/task.py"]  # protocol.Sample is the controller's S line


def test_every_user_calls_the_one_definition() -> None:
    from peel_experiments import experiment
    from peel_nachi_emulator import robot
    from peel_planner_node import control_loop
    from peel_sim_node import lockstep

    assert experiment.task_seed is robot.task_seed is lockstep.task_seed is task.task_seed
    assert experiment.mppi_seed is control_loop.mppi_seed is task.mppi_seed
    assert lockstep.Sample is control_loop.Sample is task.Sample


def test_seeds_follow_seed_sequence_and_mppi_range() -> None:
    for seed, k, stream in [(0, 0, 0), (3, 1, 0), (7, 19, 1), (2**40, 5, 0)]:
        want = int(np.random.SeedSequence([seed, stream, k]).generate_state(1)[0])
        assert task.task_seed(seed, k, stream) == want
        assert task.mppi_seed(seed, k, stream) == want % 2**31 < 2**31
    assert len({task.task_seed(3, k) for k in range(50)}) == 50
    assert task.task_seed(3, 1, 0) != task.task_seed(3, 1, 1)
