"""``peel graph``: run the ROS 2 node graph as separate OS processes (docs/graph.md).

    peel graph [--plant sim|plant|nachi] [--tasks K] [--record BAG] [--params FILE] [--seed S]
               [--effect MODULE:FUNCTION ...] [--nachi-host HOST] [--nachi-port PORT]
               [--live [PORT] [--live-host HOST]] [--out DIR [--force]] [--keep-going]
               [--verbose]

Starts ``peel_sim_node``, ``peel_planner_node`` and ``model_learner_node`` (and the recorder,
``peel record``, with ``--record``) as child processes on rclpy (``ROS_DOMAIN_ID`` is passed on;
``ROS_AUTOMATIC_DISCOVERY_RANGE`` is LOCALHOST unless set), each with its
``config/<node>.yaml``, the override file and a few ``-p`` settings, exactly as ``ros2 run``
would get them. ``--plant nachi`` starts the bridge to the Nachi robot controller
(``peel_nachi_bridge``, docs/nachi.md) at ``--nachi-host:--nachi-port`` in the simulator
bridge's place; it publishes the same topics, so nothing else changes. ``--effect`` adds a user
effect to the simulated plant (the simulator node's ``node.effects``; docs/residual.md); the
names are imported before anything starts. ``--live [PORT]`` adds the live view
(``peel_live``, :mod:`.live_node`): the running graph on a Foxglove WebSocket server at
``ws://127.0.0.1:PORT`` (default 8765; ``--live-host`` binds another address), its port checked
free before anything starts; without ``--live`` nothing imports the Foxglove SDK. Every node's
parameters are checked before anything starts (unknown names, types, ranges: one line, exit 2); a node that
refuses its parameters or files anyway (a model with non-finite outputs, too) exits 2, and so
does the graph. The planner and the bridge are managed nodes started unconfigured (``node.autostart`` false): the
launcher configures both at once, then activates the planner, then the bridge, through their
``change_state`` services (:class:`~peel_bringup.lifecycle_node.GraphBringUp`, docs/graph.md
"Lifecycle"); a node whose configure fails is shut down and exits with its error (2 bad input,
1 no controller), one that does not answer within ``graph.lifecycle_timeout_s`` counts as dead.
The launcher itself joins the graph as a listener (``peel_graph``:
``/peel/trajectory``, ``/peel/model_version``, ``/peel/model_info``, ``/peel/model_update``) and
prints one line per finished task: outcome, T_cpl, J (Eq. 3,
:func:`peel_planner_node.cost.episode_cost`) and the model version the task ran with; and one
line per update of the learner: swapped in (as which version), refused, failed or skipped, as
soon as it is known.

Before anything starts, the launcher looks ``graph.alone_wait_s`` of DDS discovery long for
another peel graph on its ROS domain (a node of a peel name, a publisher of a ``/peel`` topic)
and refuses to join one (exit 5, one line naming the domain and how to choose another): two
graphs on one domain would swap each other's models and mix their bags.

It stops cleanly after K tasks (after the learner's own report on its last update, or
``graph.final_model_wait_s``) or on Ctrl-C: SIGINT to every node, the recorder last so the bag
holds that report and is closed and readable. Exit status (:data:`EXIT_STATUS`; the first that
applies in the order 130, 2, 1, 4, 3): 0 all well; 1 a node died (named; ``--keep-going``: a dead learner or
recorder is reported but the tasks go on, the planner keeping its last good model); 2 bad input
(here or in a node), nothing started; 3 every node ran to the end but at least one update of
the learner failed or was refused (the planner kept its model); 4 the recording failed (the
recorder died or could not write, e.g. a full disk: the bag is cut short, the repair command is
printed); 5 another peel graph runs on the ROS domain, nothing started; 130 Ctrl-C. Node output
goes to ``OUT/logs/<node>.log``; ``OUT/summary.json`` holds the per-task results, each with its
update.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from peel_bag.bag import repair_hint
from peel_msgs_py import discovery
from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.cliargs import ArgumentParser, int_arg, nonnegative_int, positive_int, run_main
from peel_msgs_py.errors import DomainTaken, PeelError
from peel_msgs_py.modelinfo import SWAPPED, UpdateWait
from peel_msgs_py.outputs import OutputDir, check_location, check_new_path
from peel_msgs_py.params import load_node_params

from .children import RECORDER, Child, Interrupt, child_env, tear_down
from .node_args import LEARNER, NACHI, check_node_params, graph_params, node_command, node_settings

NODES = ("peel_sim_node", "peel_planner_node", "model_learner_node")
#: The live view's process (``--live``, :mod:`.live_node`), its default port (Foxglove's) and the
#: only address it binds by default.
LIVE = "peel_live"
LIVE_PORT = 8765
LIVE_HOST = "127.0.0.1"
#: Nodes whose death the graph survives with --keep-going.
OPTIONAL = ("model_learner_node", RECORDER, LIVE)
#: Exit status of a node (and of the graph) refusing bad input, e.g. a parameter.
BAD_INPUT = 2
#: Exit status of a graph whose nodes all ran but where an update of the learner failed.
UPDATE_FAILED = 3
#: Exit status of a graph whose recorder died or could not write (the bag needs a repair).
RECORDING_FAILED = 4
#: Exit status of a graph refused because another peel graph runs on its ROS domain.
DOMAIN_TAKEN = DomainTaken.exit_status
#: Every exit status of ``peel graph`` (module docstring; docs/graph.md).
EXIT_STATUS = {0: "ok", 1: "a node died", BAD_INPUT: "bad input",
               UPDATE_FAILED: "a model update failed",
               RECORDING_FAILED: "the recording failed (bag cut short)",
               DOMAIN_TAKEN: "another peel graph on the ROS domain", 130: "interrupted"}


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel graph", description=__doc__.split("\n\n")[0])
    p.add_argument("--plant", choices=("sim", "plant", "nachi"), default=None,
                   help="run the tasks on the simulator, the plant or the Nachi robot "
                        "controller (default: graph.plant)")
    p.add_argument("--nachi-host", default=None, metavar="HOST",
                   help="controller address for --plant nachi (default: link.host of "
                        "config/peel_nachi_bridge.yaml)")
    # range checked as the bridge's parameter link.port (one message, naming it)
    p.add_argument("--nachi-port", type=int, default=None, metavar="PORT",
                   help="controller TCP port for --plant nachi (default: link.port)")
    p.add_argument("--tasks", type=positive_int, default=None, metavar="K",
                   help="consecutive tasks, then stop (default: graph.tasks)")
    p.add_argument("--record", metavar="BAG", default=None,
                   help="record every /peel topic and /clock to this MCAP bag directory")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="ROS 2 parameter file applied on top of config/ (any node's section)")
    p.add_argument("--seed", type=nonnegative_int, default=None, help="seed of the task sequence")
    p.add_argument("--effect", action="append", default=[], metavar="MODULE:FUNCTION",
                   help="add a user effect to the simulated plant (peel_sim_node.effects "
                        "interface, docs/residual.md); repeatable")
    add_live_args(p)
    p.add_argument("--out", metavar="DIR", default=None,
                   help="run directory for models, logs, summary.json "
                        "(default: graph.out_dir/<time>)")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier run in --out (never a folder peel did not write)")
    p.add_argument("--keep-going", action="store_true",
                   help="survive the death of the learner or the recorder (exit status still 1)")
    p.add_argument("--verbose", action="store_true", help="node output on the terminal")
    return p


def add_live_args(p: ArgumentParser) -> None:
    """``--live [PORT]`` and ``--live-host HOST`` (``peel graph``, ``peel demo``)."""
    p.add_argument("--live", type=int_arg(1, 65535), nargs="?", const=LIVE_PORT, default=None,
                   metavar="PORT", help="serve the running graph on a Foxglove WebSocket "
                   f"(ws://127.0.0.1:PORT, default port {LIVE_PORT}; docs/graph.md)")
    p.add_argument("--live-host", default=LIVE_HOST, metavar="HOST",
                   help=f"address the live view binds (default {LIVE_HOST}: this machine only)")


def check_port_free(host: str, port: int) -> None:
    """Refuse a live view whose address cannot be bound (in use, not this machine's)."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
        # as the server binds: a port whose last connections linger in TIME_WAIT is free,
        # one a socket listens on is not
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            raise PeelError(f"--live: cannot serve on {host}:{port}: {exc.strerror or exc}; "
                            f"choose another port: --live PORT") from None


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


@dataclass
class Run:
    """What a graph run was asked to do, resolved and checked before anything starts."""

    override: str | None
    gp: dict[str, Any]
    tasks: int
    plant: str
    seed: int
    run_dir: Path
    bag: Path | None
    #: the Nachi bridge's ``link.*`` settings from --nachi-host / --nachi-port
    link: dict[str, Any] = field(default_factory=dict)
    #: user effects (``module:function``) for the simulator node's ``node.effects``
    effects: tuple[str, ...] = ()
    #: the run folder, checked; created by :meth:`OutputDir.create` once the graph may start
    out: OutputDir | None = None
    #: the live view's (host, port), None without ``--live``
    live: tuple[str, int] | None = None

    def settings(self) -> dict[str, dict[str, Any]]:
        """The nodes to start and their ``-p`` settings (:func:`node_settings`)."""
        return node_settings(self.plant, self.tasks, self.seed, self.run_dir,
                             self.bag is not None, self.link, self.effects,
                             self.live is not None)


def resolve(args: argparse.Namespace) -> Run:
    """Arguments + config, every node's parameters checked; PeelError on bad input."""
    override = args.params
    if override is not None and Path(override).is_dir():
        raise PeelError(f"--params: {override} is a directory, not a parameter file")
    if override is not None and not Path(override).is_file():
        raise PeelError(f"--params: no such file {override}")
    gp = graph_params(override)
    tasks = args.tasks if args.tasks is not None else gp["graph.tasks"]
    if tasks < 1:
        raise PeelError(f"--tasks must be >= 1, got {tasks}")
    seed = args.seed if args.seed is not None else gp["graph.seed"]
    if seed < 0:
        raise PeelError(f"--seed must be >= 0, got {seed}")
    run_dir = Path(args.out) if args.out else \
        Path(gp["graph.out_dir"]) / time.strftime("%Y%m%d-%H%M%S")
    out = OutputDir(run_dir, command=getattr(args, "command", "peel graph"), force=args.force)
    bag = Path(args.record) if args.record else None
    if bag is not None:  # a bag inside an earlier run that --force replaces may exist now
        replaced = out.earlier is not None and bag.resolve().is_relative_to(run_dir.resolve())
        (check_location if replaced else check_new_path)(bag, "--record")
    plant = args.plant or gp["graph.plant"]
    link = nachi_link(args.nachi_host, args.nachi_port)
    if link and plant != "nachi":
        raise PeelError("--nachi-host / --nachi-port need --plant nachi")
    effects = check_effects(args.effect, plant)
    live = None
    if args.live is not None:
        live = (args.live_host, args.live)
        check_port_free(*live)
    elif args.live_host != LIVE_HOST:
        raise PeelError("--live-host needs --live")
    run = Run(override, gp, tasks, plant, seed, run_dir, bag, link, effects, out, live)
    check_node_params(override, run.settings())
    return run  # nothing is written yet: run_graph creates the folder once the domain is free


def nachi_link(host: str | None, port: int | None) -> dict[str, Any]:
    """The Nachi bridge's ``link.host`` / ``link.port`` settings, those given (the rest from
    config/peel_nachi_bridge.yaml); checked with the bridge's other parameters."""
    return {key: value for key, value in (("link.host", host), ("link.port", port))
            if value is not None}


def check_effects(specs: Sequence[str], plant: str) -> tuple[str, ...]:
    """The ``--effect`` names, each imported here (a name that does not import, or names no
    callable, is bad input); the Nachi controller's plant is not ours to change."""
    if not specs:
        return ()
    if plant == "nachi":
        raise PeelError("--effect changes the simulated plant; it cannot be used with "
                        "--plant nachi")
    from peel_sim_node.effects import load_effect

    for spec in specs:
        load_effect(spec)
    return tuple(specs)


def live_command(run: Run) -> list[str]:
    """``python -m peel_bringup.live_node --host H --port P [--params FILE]``."""
    assert run.live is not None
    host, port = run.live
    cmd = [sys.executable, "-m", "peel_bringup.live_node", "--host", host, "--port", str(port)]
    return cmd + (["--params", str(Path(run.override).resolve())] if run.override else [])


def children_of(run: Run) -> list[Child]:
    """The recorder (first, so it hears everything), the live view and the three nodes (the
    bridge last, so its readers are there when it starts)."""
    logs = run.run_dir / "logs"
    sets = run.settings()
    children: list[Child] = []
    if run.bag is not None:
        children.append(Child(RECORDER, [sys.executable, "-m", "peel_bag.recorder_cli",
                                         "--out", str(run.bag)], logs / "recorder.log"))
    if run.live is not None:
        children.append(Child(LIVE, live_command(run), logs / f"{LIVE}.log"))
    bridge = NACHI if run.plant == "nachi" else "peel_sim_node"
    for name in ("model_learner_node", "peel_planner_node", bridge):
        children.append(Child(name, node_command(name, run.override, sets[name]),
                              logs / f"{name}.log"))
    return children


def managed_nodes(run: Run) -> list[str]:
    """The managed nodes in the order they are activated: the planner, then the bridge."""
    return ["peel_planner_node", NACHI if run.plant == "nachi" else "peel_sim_node"]


@dataclass
class Watch:
    """The launcher's view of a running graph."""

    run: Run
    children: list[Child]
    results: list[dict[str, Any]] = field(default_factory=list)
    dead: list[str] = field(default_factory=list)
    interrupted: bool = False
    bad_input: bool = False
    finished_at: float | None = None
    shown_version: int | None = None
    failed_updates: list[int] = field(default_factory=list)

    def report_tasks(self, mon: Any) -> None:
        if mon.version is not None and mon.version != self.shown_version:
            self.shown_version = mon.version
            print(f"peel graph: planner model v{mon.version} active", flush=True)
        while len(self.results) < len(mon.trajectories):
            traj = mon.trajectories[len(self.results)]
            j = _task_cost(traj, self.run.override)
            self.results.append({"task": len(self.results) + 1, "outcome": traj.outcome,
                                 "t_cpl_s": traj.t_cpl, "J": j, "sum_fx_n": traj.sum_fx,
                                 "sum_fz_n": traj.sum_fz,
                                 "model_version": traj.meta.get("model_version"),
                                 "samples": len(traj), "update": None})
            print(task_line(len(self.results), self.run.tasks, traj, j), flush=True)
        self.report_updates(mon)

    def report_updates(self, mon: Any) -> None:
        """One line per update of the learner as soon as its outcome is known (swapped in as
        version N, refused, failed, skipped); a failure is also kept for the exit status."""
        for res in self.results:
            if res["update"] is not None or (rep := mon.updates.outcome(res["task"])) is None:
                continue
            res["update"] = {"status": rep.status, "version": rep.version, "reason": rep.reason}
            line = f"update {res['task']}/{self.run.tasks}: {rep.describe()}"
            if rep.failed:
                self.failed_updates.append(res["task"])
                latest = mon.updates.latest
                line += f"; the planner keeps model v{latest.version if latest else '?'}"
            print(line, flush=True)

    def check_children(self, keep_going: bool) -> bool:
        """Report newly dead children; True when the graph must stop."""
        for child in self.children:
            code = child.poll()
            if code is not None and not child.reported:
                child.reported = True
                self.dead.append(child.name)
                if code == BAD_INPUT:
                    self.bad_input = True
                print(f"peel graph: error: node {child.name} (pid {child.pid}) died with "
                      f"exit status {code}; log {child.log}\n{child.tail()}",
                      file=sys.stderr, flush=True)
                if child.name == RECORDER:
                    self.recording_failed()
        fatal = [d for d in self.dead if not (keep_going and d in OPTIONAL)]
        return bool(fatal)

    def recording_failed(self) -> None:
        """The recorder died or could not write (exit status 4, :meth:`status`)."""
        if RECORDER not in self.dead:
            self.dead.append(RECORDER)

    @property
    def status(self) -> int:
        """The exit status: the first that applies of 130 (Ctrl-C), 2 (bad input), 1 (a node
        other than the recorder died), 4 (the recording failed), 3 (an update failed), 0."""
        if self.interrupted:
            return 130
        if self.bad_input:
            return BAD_INPUT
        if any(d != RECORDER for d in self.dead):
            return 1
        if RECORDER in self.dead:
            return RECORDING_FAILED
        return UPDATE_FAILED if self.failed_updates else 0

    def check_recorder(self, code: int | None) -> None:
        """The recorder's exit status at the stop: non-zero (e.g. a write that failed while it
        closed the bag) is a failed recording, named with the log."""
        rec = next((c for c in self.children if c.name == RECORDER), None)
        if rec is None or code in (0, None) or rec.reported:
            return
        rec.reported = True
        print(f"peel graph: error: the recorder exited with status {code}; log {rec.log}\n"
              f"{rec.tail(3)}", file=sys.stderr, flush=True)
        self.recording_failed()

    def finished(self, mon: Any) -> bool:
        """All tasks reported and the last update in (:func:`last_update_in`: the learner's own
        report, since a learner stopped before it could not say what became of its update, and
        for a swap the planner's record too), or given up on."""
        if len(self.results) < self.run.tasks:
            return False
        if self.finished_at is None:
            self.finished_at = time.monotonic()
        learner_alive = "model_learner_node" not in self.dead
        arrived = last_update_in(mon.updates, self.run.tasks)
        wait_s = self.run.gp["graph.final_model_wait_s"]
        if learner_alive and not arrived and time.monotonic() - self.finished_at < wait_s:
            return False
        if learner_alive and not arrived:
            print(f"peel graph: warning: the learner's update after task {self.run.tasks} did "
                  f"not arrive within {wait_s:g} s", file=sys.stderr)
        return True


def last_update_in(updates: UpdateWait, task: int) -> bool:
    """The learner's own report on its update after ``task`` has come and, when it says
    swapped, the planner's record of that swap too (the learner's report does not carry the
    planner's version, and the record may reach the launcher after it)."""
    rep = updates.reported(task)
    if rep is None:
        return False
    outcome = updates.outcome(task)
    return rep.status != SWAPPED or (outcome is not None and outcome.version is not None)


def watch(w: Watch, mon: Any, stop: Interrupt, keep_going: bool, up: Any) -> None:
    """Spin the monitor until the tasks are done, a node dies or the user interrupts; ``up``
    (:class:`~peel_bringup.lifecycle_node.GraphBringUp`) configures and activates the managed nodes
    meanwhile."""
    from .monitor_node import spin_once

    while True:
        spin_once(mon, 0.1)
        if (error := up.step()) is not None:
            print(f"peel graph: error: {error}", file=sys.stderr, flush=True)
            w.dead += up.late  # never came up: stopped as dead nodes are
        w.report_tasks(mon)
        if stop.signum is not None:
            print("peel graph: interrupted; stopping the nodes", file=sys.stderr, flush=True)
            w.interrupted = True
            return
        if w.check_children(keep_going) or w.finished(mon):
            return


def check_alone(mon: Any, wait_s: float) -> None:
    """Look ``wait_s`` of discovery long for another peel graph on the ROS domain; raise
    :class:`~peel_msgs_py.errors.DomainTaken` naming it as soon as one is seen."""
    from .monitor_node import spin_once

    deadline = time.monotonic() + wait_s
    while not (found := mon.peers()) and time.monotonic() < deadline:
        spin_once(mon, 0.1)
    if found:
        domain = os.environ.get(discovery.DOMAIN_VAR) or "0"
        raise DomainTaken(
            f"ROS domain {domain} already holds a peel graph ({', '.join(found[:4])}"
            f"{', ...' if len(found) > 4 else ''}); stop it, or start this one on a domain of "
            f"its own: ROS_DOMAIN_ID=<0-101> (docs/runtime.md)")


def run_graph(args: argparse.Namespace) -> int:
    """Start, watch and stop the graph; returns the exit status."""
    run = resolve(args)
    children = children_of(run)
    env = child_env()
    discovery.confine()  # the launcher's own node too

    from .lifecycle_node import GraphBringUp
    from .monitor_node import close_monitor, open_monitor

    mon = open_monitor(LEARNER)
    try:
        check_alone(mon, run.gp["graph.alone_wait_s"])
    except DomainTaken:
        close_monitor(mon)
        raise
    assert run.out is not None
    run.out.create()  # every check passed: nothing is written before this
    run.run_dir.mkdir(parents=True, exist_ok=True)
    stop = Interrupt()
    stop.install()
    w = Watch(run, children)
    try:
        for child in children:
            child.start(env, args.verbose)
            print(f"peel graph: started {child.name} (pid {child.pid})", flush=True)
        if run.live is not None:
            print(f"peel graph: live view on ws://{run.live[0]}:{run.live[1]} (Foxglove: Open "
                  f"connection; layout config/foxglove/peel_layout.json)", flush=True)
        up = GraphBringUp(mon, managed_nodes(run), run.gp["graph.lifecycle_timeout_s"])
        watch(w, mon, stop, args.keep_going, up)
    finally:
        stop.restore()
        w.check_recorder(tear_down(children, run.gp["graph.stop_timeout_s"]))
        close_monitor(mon)
    return write_summary(w, mon)


def write_summary(w: Watch, mon: Any) -> int:
    """``summary.json`` and the closing lines; returns the exit status."""
    run = w.run
    summary = {
        "plant": run.plant, "tasks": run.tasks, "seed": run.seed, "params": run.override,
        "effects": list(run.effects),
        "bag": str(run.bag) if run.bag else None, "run_dir": str(run.run_dir),
        "model_versions": sorted(set(mon.versions)), "dead_nodes": w.dead,
        "failed_updates": w.failed_updates, "results": w.results, "status": w.status,
        "bag_repair": repair_hint(run.bag) if run.bag and RECORDER in w.dead else None,
        "status_meaning": EXIT_STATUS.get(w.status, "?"),
    }
    atomic_write_text(run.run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    vers = ", ".join(f"v{v}" for v in summary["model_versions"]) or "none"
    print(f"peel graph: {len(w.results)} of {run.tasks} tasks finished; model versions {vers}; "
          f"run directory {run.run_dir}" + (f"; bag {run.bag}" if run.bag else ""), flush=True)
    if w.dead:
        print(f"peel graph: error: node(s) died: {', '.join(w.dead)}", file=sys.stderr,
              flush=True)
    if summary["bag_repair"]:
        print(f"peel graph: error: the recording failed; the bag {run.bag} is cut short: "
              f"repair it with: {summary['bag_repair']}", file=sys.stderr, flush=True)
    if w.failed_updates:
        print(f"peel graph: error: the learner's update failed after task(s) "
              f"{', '.join(map(str, w.failed_updates))}; the planner kept its model "
              f"(exit status {UPDATE_FAILED})", file=sys.stderr, flush=True)
    return w.status


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel graph``; returns the exit status."""
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    return run_graph(args)


if __name__ == "__main__":
    sys.exit(run_main("peel graph", main))
