"""``peel graph``: run the ROS 2 node graph as separate OS processes (issue 7, docs/graph.md).

    peel graph [--plant sim|plant] [--tasks K] [--record BAG] [--params FILE] [--seed S]
               [--effect MODULE:FUNCTION ...] [--out DIR] [--keep-going] [--verbose]

Starts ``peel_sim_node``, ``peel_planner_node`` and ``model_learner_node`` (and the recorder,
``peel record``, with ``--record``) as child processes on the selected runtime (``PEEL_RUNTIME``,
``ROS_DOMAIN_ID`` are passed on), each with its ``config/<node>.yaml``, the override file and a
few ``-p`` settings, exactly as ``ros2 run`` would get them. The launcher itself joins the graph
as a listener (``peel_graph``: ``/peel/trajectory``, ``/peel/model_version``) and prints one line
per finished task: outcome, T_cpl, J (Eq. 3, :func:`peel_planner_node.cost.episode_cost`) and the
model version the task ran with.

It stops cleanly after K tasks (after the learner's last swap, ``graph.final_model_wait_s``) or
on Ctrl-C: SIGINT to every node, the recorder last so the bag is closed and readable; exit
status 0, or 130 after Ctrl-C. A node that dies makes it stop the others and exit 1 naming the
node (``--keep-going``: a dead learner or recorder is reported but the tasks go on, the planner
keeping its last good model; the exit status is still 1). Node output goes to
``OUT/logs/<node>.log``; ``OUT/summary.json`` holds the per-task results.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.errors import PeelError
from peel_msgs_py.params import (
    ParamSpec,
    config_dir,
    default_param_file,
    load_node_params,
    load_param_file,
    validate_group,
)

NODE_NAME = "peel_bringup"
NODES = ("peel_sim_node", "peel_planner_node", "model_learner_node")
RECORDER = "recorder"
#: Nodes whose death the graph survives with --keep-going.
OPTIONAL = ("model_learner_node", RECORDER)

#: The ``graph:`` group of config/peel_bringup.yaml.
GRAPH_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("graph.tasks", int, 3, "consecutive tasks K", min=1),
    ParamSpec("graph.plant", str, "sim", "sim or plant", choices=("sim", "plant")),
    ParamSpec("graph.seed", int, 0, "seed of the task sequence", min=0),
    ParamSpec("graph.out_dir", str, "runs/graph", "parent of the run directories"),
    ParamSpec("graph.final_model_wait_s", float, 300.0,
              "wall s to wait for the learner's swap after the last task", min=0.0),
    ParamSpec("graph.stop_timeout_s", float, 20.0,
              "wall s a node gets to exit after SIGINT before SIGTERM / SIGKILL", min=0.1),
)


def graph_params(override: str | None) -> dict[str, Any]:
    """The validated ``graph.*`` parameters: shipped config/peel_bringup.yaml + override file."""
    flat = load_node_params(NODE_NAME, override)
    return validate_group(GRAPH_SPECS, flat, "graph")


def _p(name: str, value: Any) -> list[str]:
    """``-p name:=value`` with a YAML-safe value."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, (str, list)):
        text = json.dumps(value)  # a quoted YAML string / a flow sequence of them
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
                  effects: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """The ``-p`` settings the launcher gives each node (``effects``: the sim node's
    ``node.effects``, user effects added to the plant)."""
    sim: dict[str, Any] = {
        "use_sim_time": True, "node.source": plant, "node.tasks": tasks, "node.seed": seed,
        "node.min_subscribers": 2 if recording else 1,  # planner (+ recorder)
        "node.min_traj_subscribers": 3 if recording else 2,  # learner, launcher (+ rec.)
    }
    if effects:
        sim["node.effects"] = list(effects)
    return {
        "peel_sim_node": sim,
        "peel_planner_node": {"use_sim_time": True, "node.seed": seed},
        "model_learner_node": {
            "use_sim_time": True, "node.out_dir": str((run_dir / "models").resolve()),
        },
    }


def _child_setup() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Own process group (one Ctrl-C is handled in order by the launcher); SIGTERM to the child
    when the launcher dies (Linux PR_SET_PDEATHSIG)."""
    os.setpgrp()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: children then rely on the launcher's stop
        pass


@dataclass
class Child:
    """One started process."""

    name: str
    cmd: list[str]
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    stopping: bool = False
    reported: bool = False

    def start(self, env: dict[str, str], verbose: bool) -> None:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        out = None if verbose else self.log.open("wb")
        try:
            self.proc = subprocess.Popen(self.cmd, stdout=out, stderr=subprocess.STDOUT
                                         if out is not None else None, env=env,
                                         preexec_fn=_child_setup)
        finally:
            if out is not None:
                out.close()

    @property
    def pid(self) -> int:
        return self.proc.pid if self.proc is not None else -1

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, sig)

    def stop(self, timeout_s: float) -> int | None:
        """SIGINT, then SIGTERM, then SIGKILL; returns the exit status."""
        if self.proc is None:
            return None
        self.stopping = True
        for sig, wait in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 5.0),
                          (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            self.signal(sig)
            try:
                self.proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        return self.proc.poll()

    def tail(self, n: int = 8) -> str:
        try:
            lines = self.log.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join("    " + line for line in lines[-n:])


@dataclass
class Monitor:
    """What the launcher hears on the graph."""

    trajectories: list[Any] = field(default_factory=list)
    version: int | None = None
    versions: list[int] = field(default_factory=list)


class _Interrupt:
    """SIGINT / SIGTERM set a flag; the launcher then stops the graph in order."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)

    def _handle(self, signum: int, frame: Any) -> None:
        self.signum = signum

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="peel graph", description=__doc__.split("\n\n")[0])
    p.add_argument("--plant", choices=("sim", "plant"), default=None,
                   help="run the tasks on the simulator or on the plant (default: graph.plant)")
    p.add_argument("--tasks", type=int, default=None, metavar="K",
                   help="consecutive tasks, then stop (default: graph.tasks)")
    p.add_argument("--record", metavar="BAG", default=None,
                   help="record every /peel topic and /clock to this MCAP bag directory")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="ROS 2 parameter file applied on top of config/ (any node's section)")
    p.add_argument("--seed", type=int, default=None, help="seed of the task sequence")
    p.add_argument("--effect", action="append", default=[], metavar="MODULE:FUNCTION",
                   help="add a user effect to the plant (peel_sim_node.effects interface); "
                        "repeatable")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="run directory for models, logs, summary.json "
                        "(default: graph.out_dir/<time>)")
    p.add_argument("--keep-going", action="store_true",
                   help="survive the death of the learner or the recorder (exit status still 1)")
    p.add_argument("--verbose", action="store_true", help="node output on the terminal")
    return p


def _task_cost(traj: Any, override: str | None) -> float:
    from peel_planner_node.config import PlannerConfig
    from peel_planner_node.cost import Cost, episode_cost

    cfg = PlannerConfig.from_params(load_node_params("peel_planner_node", override))
    return float(episode_cost(traj, Cost(cfg.cost)))


def task_line(i: int, k: int, traj: Any, j: float) -> str:
    """The line printed per finished task."""
    v = traj.meta.get("model_version")
    return (f"task {i}/{k}: {traj.outcome:<11s} T_cpl={traj.t_cpl:5.1f} s  J={j:7.2f}  "
            f"sum|Fx|={traj.sum_fx:7.1f} N  sum|Fz|={traj.sum_fz:7.1f} N  "
            f"model v{v if v is not None else '?'}")


def run_graph(args: argparse.Namespace) -> int:
    """Start, watch and stop the graph; returns the exit status."""
    override = args.params
    if override is not None and not Path(override).is_file():
        raise PeelError(f"--params: no such file {override}")
    gp = graph_params(override)
    for name in NODES:  # a bad override file fails here, before anything starts
        if default_param_file(name).is_file():
            load_param_file(default_param_file(name), name)
        if override:
            load_param_file(override, name)
    tasks = args.tasks if args.tasks is not None else gp["graph.tasks"]
    if tasks < 1:
        raise PeelError(f"--tasks must be >= 1, got {tasks}")
    plant = args.plant or gp["graph.plant"]
    seed = args.seed if args.seed is not None else gp["graph.seed"]
    if seed < 0:
        raise PeelError(f"--seed must be >= 0, got {seed}")
    run_dir = Path(args.out) if args.out else \
        Path(gp["graph.out_dir"]) / time.strftime("%Y%m%d-%H%M%S")
    bag = Path(args.record) if args.record else None
    if bag is not None and bag.exists():
        raise PeelError(f"--record: {bag} already exists")
    if args.effect:  # fail here, before anything starts, on a name that does not import
        from peel_sim_node.effects import load_effects

        load_effects(args.effect)
    run_dir.mkdir(parents=True, exist_ok=True)

    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("PEEL_CONFIG_DIR", str(config_dir()))
    env.setdefault("OMP_NUM_THREADS", "1")
    sets = node_settings(plant, tasks, seed, run_dir, bag is not None, args.effect)
    children: list[Child] = []
    if bag is not None:
        children.append(Child(RECORDER, [sys.executable, "-m", "peel_msgs_py.recorder_cli",
                                         "--out", str(bag)], run_dir / "logs" / "recorder.log"))
    for name in ("model_learner_node", "peel_planner_node", "peel_sim_node"):
        children.append(Child(name, node_command(name, override, sets[name]),
                              run_dir / "logs" / f"{name}.log"))

    from peel_msgs_py import codec, topics
    from peel_msgs_py.runtime import Node, rclpy
    from peel_msgs_py.runtime.msg import Float64MultiArray, Int64

    mon = Monitor()
    rclpy.init(args=None)
    stop = _Interrupt()
    stop.install()
    node = Node("peel_graph")

    def on_traj(msg: Any) -> None:
        try:
            mon.trajectories.append(codec.trajectory_from_msg(msg))
        except PeelError as exc:
            print(f"peel graph: warning: bad /peel/trajectory message: {exc}", file=sys.stderr)

    def on_version(msg: Any) -> None:
        mon.version = int(msg.data)
        mon.versions.append(int(msg.data))

    node.create_subscription(Float64MultiArray, topics.TRAJECTORY, on_traj,
                             topics.qos_profile(topics.TRAJECTORY, subscriber=True))
    # deeper reader history than the latched profile's 1, so quick successive swaps are all seen
    node.create_subscription(Int64, topics.MODEL_VERSION, on_version, topics.qos_profile(
        dataclasses.replace(topics.topic(topics.MODEL_VERSION).sub_qos, depth=16)))

    status = 0
    dead: list[str] = []
    results: list[dict[str, Any]] = []
    try:
        for child in children:
            child.start(env, args.verbose)
            print(f"peel graph: started {child.name} (pid {child.pid})", flush=True)
        printed = 0
        finished_at: float | None = None
        start_version: int | None = None
        shown_version: int | None = None
        while True:
            rclpy.spin_once(node, timeout_sec=0.1)
            if start_version is None and mon.version is not None:
                start_version = mon.version
            if mon.version is not None and mon.version != shown_version:
                shown_version = mon.version
                print(f"peel graph: planner model v{shown_version} active", flush=True)
            while printed < len(mon.trajectories):
                traj = mon.trajectories[printed]
                printed += 1
                j = _task_cost(traj, override)
                results.append({"task": printed, "outcome": traj.outcome, "t_cpl_s": traj.t_cpl,
                                "J": j, "sum_fx_n": traj.sum_fx, "sum_fz_n": traj.sum_fz,
                                "model_version": traj.meta.get("model_version"),
                                "samples": len(traj)})
                print(task_line(printed, tasks, traj, j), flush=True)
            if stop.signum is not None:
                print("peel graph: interrupted; stopping the nodes", file=sys.stderr, flush=True)
                status = 130
                break
            for child in children:
                code = child.poll()
                if code is not None and not child.reported:
                    child.reported = True
                    dead.append(child.name)
                    print(f"peel graph: error: node {child.name} (pid {child.pid}) died with "
                          f"exit status {code}; log {child.log}\n{child.tail()}",
                          file=sys.stderr, flush=True)
            fatal = [d for d in dead if not (args.keep_going and d in OPTIONAL)]
            if fatal:
                status = 1
                break
            if printed >= tasks:
                if finished_at is None:
                    finished_at = time.monotonic()
                learner_alive = "model_learner_node" not in dead
                want = (start_version or 0) + tasks
                waited = time.monotonic() - finished_at
                if (not learner_alive or (mon.version or 0) >= want
                        or waited >= gp["graph.final_model_wait_s"]):
                    if learner_alive and (mon.version or 0) < want:
                        print(f"peel graph: warning: model version {want} did not arrive within "
                              f"{gp['graph.final_model_wait_s']:g} s", file=sys.stderr)
                    break
        if dead:
            status = status or 1
    finally:
        stop.restore()
        for child in children:  # nodes first (sim stops producing), recorder last
            if child.name != RECORDER:
                child.signal(signal.SIGINT)
        for child in children:
            if child.name != RECORDER:
                child.stop(gp["graph.stop_timeout_s"])
        for child in children:
            if child.name == RECORDER:
                time.sleep(0.5)  # let the last messages reach the recorder
                code = child.stop(gp["graph.stop_timeout_s"])
                if code not in (0, None) and child.name not in dead:
                    print(f"peel graph: warning: the recorder exited with status {code}; "
                          f"log {child.log}", file=sys.stderr)
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()

    summary = {
        "plant": plant, "tasks": tasks, "seed": seed, "params": override,
        "effects": list(args.effect),
        "bag": str(bag) if bag else None, "run_dir": str(run_dir),
        "model_versions": sorted(set(mon.versions)), "dead_nodes": dead,
        "results": results, "status": status,
    }
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    vers = ", ".join(f"v{v}" for v in summary["model_versions"]) or "none"
    print(f"peel graph: {len(results)} of {tasks} tasks finished; model versions {vers}; "
          f"run directory {run_dir}" + (f"; bag {bag}" if bag else ""), flush=True)
    if dead:
        print(f"peel graph: error: node(s) died: {', '.join(dead)}", file=sys.stderr, flush=True)
    return status


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel graph``; returns the exit status."""
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    return run_graph(args)


if __name__ == "__main__":
    sys.exit(main())
