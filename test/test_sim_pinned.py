"""Pinned simulator output: what ``source="sim"`` produces for a seed must not change.

Other packages train on simulator data and plan against ``PeelEnv``; performance work on the
engine loop and plant-side changes must leave the simulator's numbers bit-identical. The
digests below are the SHA-256 of the float64 little-endian bytes; a change of any value, however
small, fails. They were last re-pinned when q became the robot carriage's (encoder) position
instead of the blade's (forces unchanged, see docs/simulator.md); re-pin only on purpose, and
then regenerate the shipped checkpoint (model_learner_node/checkpoints/PROVENANCE.md).
"""

import hashlib

import numpy as np

from peel_sim_node.config import load_sim_config
from peel_sim_node.dataset import generate_set
from peel_sim_node.env import PeelEnv

CFG = load_sim_config()
CMDS = [1.0, 2.5, 4.0, 6.0, 3.0, 0.5, 8.0, 2.0]


def digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def test_sim_trajectory_and_rollout_are_pinned():
    with PeelEnv(CFG, seed=7) as env:
        outs = []
        for k in range(40):
            env.step(CMDS[k // 5])
            if k == 19:
                v = np.array([[2.0] * 6, [5.0] * 6, np.linspace(0.5, 8.0, 6)])
                outs.append(env.rollout(v))
        h = env.history
    assert h.outcome == "running" and len(h) == 41
    # readable spot values first (a failure shows where), then every bit
    assert h.q[-1] == 13.570200356396244
    assert h.fx[-1] == 12.64
    assert outs[0][2, -1].tolist() == [9.363637315652754, 13.684839761111368, 9.704338273315495]
    assert digest(h.as_array()) == (
        "9046088444477380d82aa940212aebdf613dc3b438ef7ed6ce58729d7543aa9c")
    assert digest(*outs) == "fdeda25311e2a2879deda0da90a0dc8217962fd5046ffb387f04281278ededc5"


def test_sim_dataset_trajectories_are_pinned():
    """The trajectories `peel dataset --source sim` writes for set 3 of seed 5."""
    trs = generate_set(CFG, 3, 2, 5, "sim")
    assert [(t.outcome, len(t)) for t in trs] == [("done", 81), ("done", 88)]
    assert [t.meta["env_seed"] for t in trs] == [6274229382737886243, 3461401157248930251]
    assert trs[0].q[-1] == 25.432982252138427 and trs[1].fx[-1] == 9.81
    assert [digest(t.as_array()) for t in trs] == [
        "8acc23605e320d4d77e8935fb8f84e1f7e7ff22109d55cb399c4924daa902509",
        "5208ba0b5ba8c54d19be4c1709cff9bb5668a7a257750339cc71f3ecc1793858",
    ]
