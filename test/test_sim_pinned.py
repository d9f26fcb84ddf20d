"""Pinned simulator output: what ``source="sim"`` produces for a seed must not change.

Other packages train on simulator data and plan against ``PeelEnv``; performance work on the
engine loop and plant-side changes must leave the simulator's numbers bit-identical. The
digests below were computed from the simulator before the rollout / stepping optimisations
(the SHA-256 of the float64 little-endian bytes); a change of any value, however small, fails.
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
    assert h.q[-1] == 9.453733794313644
    assert h.fx[-1] == 12.64
    assert outs[0][2, -1].tolist() == [5.286448215990943, 13.684839761111368, 9.704338273315495]
    assert digest(h.as_array()) == (
        "c25035d125ee8bb77de05e23702fb6716da4bfcd8322bc8d9d48aee5dfc4a34c")
    assert digest(*outs) == "5b641e41b44e3008cb67b088cfc4b69a8e30e72f8c76f82f7a6580cc05327deb"


def test_sim_dataset_trajectories_are_pinned():
    """The trajectories `peel dataset --source sim` writes for set 3 of seed 5."""
    trs = generate_set(CFG, 3, 2, 5, "sim")
    assert [(t.outcome, len(t)) for t in trs] == [("done", 89), ("done", 115)]
    assert [t.meta["env_seed"] for t in trs] == [6274229382737886243, 3461401157248930251]
    assert trs[0].q[-1] == 25.385562843194627 and trs[1].fx[-1] == 6.47
    assert [digest(t.as_array()) for t in trs] == [
        "4eec5e7916b9255b961ae113326af93582de7dc72105edfe203d7adefd24469e",
        "492a4014c514f8c4f8c7a1e07352355f7d8d34721375e967662f607b85596ea7",
    ]
