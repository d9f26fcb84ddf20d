"""The nodes ``peel graph`` and ``peel fleet`` start, as ``ros2 run`` would start them
(docs/graph.md): each node's command line (its shipped ``config/<node>.yaml``, the override
file, the launcher's ``-p`` settings), those settings, and the check of every parameter before
anything starts (unknown names, types, ranges: one line, exit 2)."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from peel_msgs_py.params import default_param_file, load_node_params, validate

from .parameters import GRAPH_SPECS

NODE_NAME = "peel_bringup"
#: The node that stands in for ``peel_sim_node`` with ``--plant nachi`` (docs/nachi.md).
NACHI = "peel_nachi_bridge"
#: The learner whose updates the launcher (and the simulator: its ``node.learner_node``) waits
#: for, by its identity on ``/peel/model_info`` (the learner's fully qualified node name).
LEARNER = "/model_learner_node"
#: The managed nodes start unconfigured; the launcher drives their transitions (:mod:`.lifecycle_node`).
MANAGED = {"node.autostart": False}


def graph_params(override: str | None) -> dict[str, Any]:
    """The validated ``graph.*`` parameters: shipped config/peel_bringup.yaml + override file."""
    flat = load_node_params(NODE_NAME, override)
    return validate(GRAPH_SPECS, {k: v for k, v in flat.items() if k.startswith("graph.")})


def node_specs(name: str) -> tuple[Any, ...]:
    """Every parameter node ``name`` declares (its package's ``parameters.SPECS``)."""
    import importlib

    return tuple(importlib.import_module(f"{name}.parameters").SPECS)


def check_node_params(override: str | None, sets: dict[str, dict[str, Any]]) -> None:
    """Refuse, before any process starts, what a node would refuse at its start: unknown names
    (sections of the files included), wrong types (an integer for a DOUBLE too), values out of
    range, with the parameter named (:class:`~peel_msgs_py.errors.ParameterError`). ``sets``
    names the nodes to start and their ``-p`` settings."""
    for name, settings in sets.items():
        specs = node_specs(name)
        known = {s.name for s in specs}
        # /** names this node does not declare are for other nodes (checked by the loader)
        flat = {k: v for k, v in load_node_params(name, override).items() if k in known}
        values = validate(specs, {**flat, **settings})
        if name == NACHI:  # what the bridge checks across its parameters (host, backoff)
            from peel_nachi_bridge.config import BridgeConfig

            BridgeConfig.from_params(values)


def _p(name: str, value: Any) -> list[str]:
    """``-p name:=value`` with a YAML-safe value."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, (str, list)):
        text = json.dumps(value)  # a quoted YAML string, or a flow sequence of them
    else:
        text = repr(value)
    return ["-p", f"{name}:={text}"]


def node_command(name: str, override: str | None, sets: dict[str, Any]) -> list[str]:
    """``python -m <pkg>.node --ros-args --params-file ... -p ...`` for one node."""
    cmd = [sys.executable, "-m", f"{name}.node", "--ros-args"]
    shipped = default_param_file(name)
    if shipped.is_file():
        cmd += ["--params-file", str(shipped)]
    if override:
        cmd += ["--params-file", str(Path(override).resolve())]
    for key, value in sets.items():
        cmd += _p(key, value)
    return cmd


def node_settings(plant: str, tasks: int, seed: int, run_dir: Path, recording: bool,
                  link: dict[str, Any] | None = None, effects: Sequence[str] = (),
                  live: bool = False) -> dict[str, dict[str, Any]]:
    """The nodes to start and the ``-p`` settings the launcher gives each: the simulator bridge
    (``plant`` sim or plant; ``effects``: its ``node.effects``) or the Nachi bridge (``plant``
    nachi; ``link``: its ``link.host``, ``link.port``), the planner and the learner. The
    recorder and the live view (``live``) are readers the bridge and the planner wait for."""
    tools = int(recording) + int(live)
    readers = {"node.min_subscribers": 1 + tools,  # planner (+ recorder, live view)
               "node.min_traj_subscribers": 2 + tools}  # learner, launcher (+ ...)
    if plant == "nachi":  # the substrates and the plant are the controller's
        bridge = {NACHI: {"use_sim_time": True, "node.tasks": tasks, **readers,
                          "node.learner_node": LEARNER, **MANAGED, **(link or {})}}
    else:
        bridge = {"peel_sim_node": {"use_sim_time": True, "node.source": plant,
                                    "node.tasks": tasks, "node.seed": seed, **readers,
                                    "node.learner_node": LEARNER, **MANAGED}}
        if effects:
            bridge["peel_sim_node"]["node.effects"] = list(effects)
    return {
        **bridge,
        "peel_planner_node": {"use_sim_time": True, "node.seed": seed, **MANAGED,
                              "node.min_cmd_subscribers": 1 + tools},  # bridge (+ rec., live)
        "model_learner_node": {
            "use_sim_time": True, "node.out_dir": str((run_dir / "models").resolve()),
        },
    }
