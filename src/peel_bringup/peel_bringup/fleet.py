"""``peel fleet``: K peeling cells and one learner as separate processes (docs/fleet.md).

    peel fleet --cells 3 --tasks 2 [--plant sim|plant] [--seed S] [--record BAG] [--out DIR]
    peel fleet --plant nachi --nachi-controllers HOST:PORT[,HOST:PORT...] [--cells K] ...

Cell c runs under the namespace ``/cell_<c>`` (every topic and the planner's services move with
it, docs/graph.md): a simulator bridge on its own task sequence (``node.seed`` =
:func:`cell_seed`: the plant randomized per cell) and a planner. With ``--plant nachi`` cell c
runs the Nachi bridge to the c-th controller of ``--nachi-controllers`` instead (one controller
per cell; ``--cells``, when given, must be their number). One learner, at the root,
serves every cell (``node.cells``, :mod:`model_learner_node.cells_node`): it learns the pooled
peels in (task, cell) order and swaps each update into every cell's planner. The launcher
prints a line per finished task and per update, each naming its cell; a cell whose node dies
is reported and its other processes stopped while the other cells and the learner go on; the
run then exits 1. ``--join-after U`` starts the last cell only once U updates were swapped in
(a cell that joins late: the learner gives it the current model before its first task).

``--record BAG`` writes one bag per cell, ``BAG/cell_<c>``, each in the one-cell layout (the
cell's topics under ``/peel/...``, ``peel record --cell``): every bag tool reads it as it
reads a ``peel graph`` bag, a cell machine records its own 10 Hz streams locally instead of
sending them to one recorder, and a cell that dies cuts only its own bag.

Output: the lines above, ``OUT/summary.json`` and, last, the summary as one JSON line. Exit
status (the first that applies): 130 Ctrl-C, 2 bad input, 1 a cell's node or the learner
died, 3 an update failed or was refused at the cell it came from, 0 all well; 5 another peel
graph is on the ROS domain (nothing started).
"""

from __future__ import annotations

import json
import os
import re
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from model_learner_node.cells import cell_producer
from peel_msgs_py import discovery
from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int, run_main
from peel_msgs_py.errors import DomainTaken, PeelError
from peel_msgs_py.modelinfo import SWAPPED
from peel_msgs_py.outputs import OutputDir, check_new_path
from peel_msgs_py.params import load_node_params
from peel_msgs_py.task import mppi_seed

from .children import Child, Interrupt, child_env, tear_down
from .fleet_report import update_times
from .graph import BAD_INPUT, UPDATE_FAILED, _task_cost, nachi_link, task_line
from .node_args import LEARNER, NACHI, check_node_params, graph_params, node_command, node_settings, node_specs

LEARNER_NODE = "model_learner_node"
#: Stream of :func:`~peel_msgs_py.task.task_seed` the cells' seeds are drawn from.
CELL_SEED_STREAM = 7
#: Cells of a run on the simulator when --cells is not given.
DEFAULT_CELLS = 2
#: A controller of ``--nachi-controllers``: (host, port).
Controller = tuple[str, int]


def file_number(path: str) -> int:
    """NNNN of the learner's ``model_vNNNN.safetensors`` (its order of updates); 0 for others."""
    m = re.search(r"model_v(\d+)", Path(path).name)
    return int(m.group(1)) if m else 0


def cell_name(c: int) -> str:
    return f"/cell_{c}"


def cell_seed(seed: int, c: int) -> int:
    """``node.seed`` of cell c: the run's seed for cell 0 (so one cell is ``peel graph``'s
    task sequence), a seed drawn from (seed, c) for every other cell."""
    return seed if c == 0 else mppi_seed(seed, c, CELL_SEED_STREAM)


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel fleet", description=__doc__.split("\n\n")[0])
    p.add_argument("--cells", type=positive_int, default=None, metavar="K",
                   help=f"peeling cells, each a bridge and a planner (default {DEFAULT_CELLS}; "
                        "with --plant nachi the number of controllers)")
    p.add_argument("--tasks", type=positive_int, default=None, metavar="T",
                   help="consecutive tasks per cell (default: graph.tasks)")
    p.add_argument("--plant", choices=("sim", "plant", "nachi"), default=None,
                   help="every cell on the simulator, the plant, or a Nachi robot controller of "
                        "its own (--nachi-controllers) (default: graph.plant)")
    p.add_argument("--nachi-controllers", default=None, metavar="HOST:PORT[,HOST:PORT...]",
                   help="with --plant nachi: one controller per cell, cell c on the c-th")
    p.add_argument("--seed", type=nonnegative_int, default=None,
                   help="seed of the run; each cell's task sequence seed is derived from it")
    p.add_argument("--record", metavar="BAG", default=None,
                   help="a bag per cell: BAG/cell_<c> (one-cell layout)")
    p.add_argument("--join-after", type=positive_int, default=None, metavar="U",
                   help="start the last cell once U updates were swapped in (a late cell)")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="ROS 2 parameter file applied on top of config/ (any node's section)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="run directory (default: graph.out_dir/fleet-<time>)")
    p.add_argument("--force", action="store_true", help="replace an earlier run in --out")
    p.add_argument("--verbose", action="store_true", help="node output on the terminal")
    return p


@dataclass
class FleetRun:
    """What a fleet run was asked to do, resolved and checked before anything starts."""

    override: str | None
    gp: dict[str, Any]
    cells: list[str]
    tasks: int
    plant: str
    seed: int
    run_dir: Path
    bag: Path | None
    join_after: int | None
    out: OutputDir
    controllers: list[Controller] = field(default_factory=list)  # --plant nachi: one per cell

    @property
    def bridge(self) -> str:
        """The node that drives each cell's plant: the simulator's or the Nachi bridge."""
        return NACHI if self.plant == "nachi" else "peel_sim_node"

    def controller(self, c: int) -> str | None:
        """Cell c's controller as ``HOST:PORT`` (None on the simulator)."""
        return controller_name(*self.controllers[c]) if self.controllers else None

    def settings(self) -> dict[str, dict[str, dict[str, Any]]]:
        """cell -> node -> ``-p`` settings, and ``""`` -> the learner's."""
        sets: dict[str, dict[str, dict[str, Any]]] = {}
        for c, cell in enumerate(self.cells):
            link = nachi_link(*self.controllers[c]) if self.controllers else None
            nodes = node_settings(self.plant, self.tasks, cell_seed(self.seed, c), self.run_dir,
                                  self.bag is not None, link=link)
            nodes.pop(LEARNER_NODE)
            nodes[self.bridge]["node.learner_node"] = cell_producer(LEARNER, cell)
            for name in (self.bridge, "peel_planner_node"):  # a cell's nodes bring
                nodes[name]["node.autostart"] = True  # themselves up (configure + activate)
            sets[cell] = nodes
        sets[""] = {LEARNER_NODE: {"use_sim_time": False, "node.cells": list(self.cells),
                                   "node.out_dir": str((self.run_dir / "models").resolve())}}
        return sets


def controller_name(host: str, port: int) -> str:
    """``HOST:PORT`` (an IPv6 host in brackets)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def parse_controller(item: str) -> Controller:
    """One ``HOST:PORT`` (IPv6: ``[ADDR]:PORT``); PeelError naming it when malformed."""
    host, sep, port = item.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        host = ""  # a bare IPv6 address: which colon ends it is ambiguous
    if not sep or not host or any(ch.isspace() for ch in host) or \
            not re.fullmatch(r"[0-9]+", port):
        raise PeelError(f"--nachi-controllers: {item!r} is not HOST:PORT "
                        f"(an IPv6 address as [ADDR]:PORT)")
    if not 1 <= int(port) <= 65535:
        raise PeelError(f"--nachi-controllers: port {port} of {item!r} is not in 1..65535")
    return host, int(port)


def parse_controllers(text: str) -> list[Controller]:
    """``HOST:PORT[,HOST:PORT...]`` in cell order; PeelError on a malformed or repeated one."""
    out: list[Controller] = []
    for item in text.split(","):
        host, port = parse_controller(item.strip())
        if (host.lower(), port) in [(h.lower(), p) for h, p in out]:
            raise PeelError(f"--nachi-controllers: {item.strip()} is given twice "
                            f"(one controller per cell)")
        out.append((host, port))
    return out


def fleet_cells(args: Any, plant: str) -> tuple[int, list[Controller]]:
    """The number of cells and, with ``--plant nachi``, each cell's controller (one per cell:
    ``--cells`` defaults to their number and must match it when given)."""
    text = getattr(args, "nachi_controllers", None)
    if plant != "nachi":
        if text is not None:
            raise PeelError("--nachi-controllers needs --plant nachi")
        return (args.cells if args.cells is not None else DEFAULT_CELLS), []
    if text is None:
        raise PeelError("--plant nachi needs --nachi-controllers HOST:PORT[,HOST:PORT...] "
                        "(one controller per cell)")
    controllers = parse_controllers(text)
    if args.cells is not None and args.cells != len(controllers):
        raise PeelError(f"--cells {args.cells} but {len(controllers)} controller(s) in "
                        f"--nachi-controllers: one controller per cell")
    return len(controllers), controllers


def resolve(args: Any) -> FleetRun:
    """Arguments + config, every node's parameters checked; PeelError on bad input."""
    override = args.params
    if override is not None and not Path(override).is_file():
        raise PeelError(f"--params: no such file {override}")
    gp = graph_params(override)
    plant = args.plant or gp["graph.plant"]
    cells, controllers = fleet_cells(args, plant)
    if args.join_after is not None and cells < 2:
        raise PeelError("--join-after needs --cells 2 or more (the last cell joins late)")
    run_dir = Path(args.out) if args.out else \
        Path(gp["graph.out_dir"]) / time.strftime("fleet-%Y%m%d-%H%M%S")
    out = OutputDir(run_dir, command="peel fleet", force=args.force)
    bag = Path(args.record) if args.record else None
    if bag is not None:
        check_new_path(bag, "--record")
    run = FleetRun(override, gp, [cell_name(c) for c in range(cells)],
                   args.tasks if args.tasks is not None else gp["graph.tasks"], plant,
                   args.seed if args.seed is not None else gp["graph.seed"], run_dir, bag,
                   args.join_after, out, controllers)
    for nodes in run.settings().values():
        check_node_params(override, nodes)
    return run


def file_settings(name: str, override: str | None) -> dict[str, Any]:
    """What node ``name``'s sections of config/<name>.yaml and the override file set (values
    other than its declared defaults), as ``-p`` settings: rcl applies a ``<name>:`` section to
    the node at the root only, never to ``/cell_<c>/<name>``, so a cell's nodes get them on the
    command line (``-p`` settings apply under any namespace)."""
    values = load_node_params(name, override)
    return {s.name: values[s.name] for s in node_specs(name)
            if s.name in values and values[s.name] != s.default}


def children_of(run: FleetRun) -> tuple[list[Child], dict[str, list[Child]]]:
    """The learner, and per cell its recorder (with --record), planner and bridge (last)."""
    logs = run.run_dir / "logs"
    sets = run.settings()
    learner = Child(LEARNER_NODE, node_command(LEARNER_NODE, run.override, sets[""][LEARNER_NODE]),
                    logs / f"{LEARNER_NODE}.log")
    cells: dict[str, list[Child]] = {}
    for cell in run.cells:
        here = logs / cell.strip("/")
        kids = []
        if run.bag is not None:
            kids.append(Child(f"{cell}/recorder", [
                sys.executable, "-m", "peel_bag.recorder_cli", "--out",
                str(run.bag / cell.strip("/")), "--cell", cell], here / "recorder.log"))
        for name in ("peel_planner_node", run.bridge):
            here_sets = {**file_settings(name, run.override), **sets[cell][name]}
            cmd = [*node_command(name, run.override, here_sets), "-r", f"__ns:={cell}"]
            kids.append(Child(f"{cell}/{name}", cmd, here / f"{name}.log"))
        cells[cell] = kids
    return [learner], cells


@dataclass
class FleetWatch:
    """The launcher's view of the running cells."""

    run: FleetRun
    learner: list[Child]
    cells: dict[str, list[Child]]
    mons: dict[str, Any]
    t0: float = field(default_factory=time.monotonic)
    results: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    dead: list[str] = field(default_factory=list)  # "<cell>" or the learner
    started: set[str] = field(default_factory=set)
    bad_input: bool = False
    interrupted: bool = False
    failed_updates: list[str] = field(default_factory=list)
    finished_at: float | None = None

    def start(self, cell: str, env: dict[str, str], verbose: bool) -> None:
        self.started.add(cell)
        for child in self.cells[cell]:
            child.start(env, verbose)
            print(f"peel fleet: started {child.name} (pid {child.pid})", flush=True)

    def report(self) -> None:
        """A line per finished task and per update, each naming its cell."""
        for cell, mon in self.mons.items():
            res = self.results.setdefault(cell, [])
            while len(res) < len(mon.trajectories):
                traj = mon.trajectories[len(res)]
                j = _task_cost(traj, self.run.override)
                res.append({"task": len(res) + 1, "outcome": traj.outcome, "J": j,
                            "t_cpl_s": traj.t_cpl, "model_version": traj.meta.get("model_version"),
                            "model_sha256": started_on(traj.meta),
                            "wall_s": round(time.monotonic() - self.t0, 2), "update": None})
                print(f"{cell} {task_line(len(res), self.run.tasks, traj, j)}", flush=True)
            for r in res:
                if r["update"] is None and (rep := mon.updates.outcome(r["task"])) is not None:
                    r["update"] = {"status": rep.status, "version": rep.version,
                                   "reason": rep.reason}
                    if rep.failed:
                        self.failed_updates.append(f"{cell}:{r['task']}")
                    print(f"{cell} update {r['task']}/{self.run.tasks}: {rep.describe()}",
                          flush=True)

    def swapped(self) -> int:
        return sum(1 for res in self.results.values() for r in res
                   if r["update"] and r["update"]["status"] == SWAPPED)

    def check_children(self) -> None:
        """A dead node: its cell is reported dead and its other processes stopped."""
        groups = {**self.cells, "": self.learner}
        for cell, kids in groups.items():
            for child in kids:
                code = child.poll()
                if code is None or child.reported:
                    continue
                child.reported = True
                if child.stopping:
                    continue
                self.bad_input |= code == BAD_INPUT
                who = f"cell {cell}" if cell else "the learner"
                self.dead.append(cell or LEARNER_NODE)
                print(f"peel fleet: error: {who}: node {child.name} (pid {child.pid}) died with "
                      f"exit status {code}; log {child.log}\n{child.tail()}", file=sys.stderr,
                      flush=True)
                for other in kids:
                    other.stopping = True
                    other.signal(signal.SIGINT)

    def live_cells(self) -> list[str]:
        return [c for c in self.run.cells if c not in self.dead]

    def finished(self) -> bool:
        """Every live cell's tasks reported, the learner's report on each cell's last one in
        and every update at every live cell (:meth:`unseen`), or given up on after
        ``graph.final_model_wait_s``."""
        live = self.live_cells()
        if any(len(self.results.get(c, [])) < self.run.tasks for c in live):
            return False
        self.finished_at = self.finished_at or time.monotonic()
        if LEARNER_NODE in self.dead:
            return True
        waiting = [c for c in live if self.mons[c].updates.reported(self.run.tasks) is None]
        return not (waiting or self.unseen()) or time.monotonic() - self.finished_at > \
            self.run.gp["graph.final_model_wait_s"]

    def unseen(self) -> list[tuple[str, str, int]]:
        """(cell, producer, task) of every update swapped in at the cell it came from that a
        live cell's planner has not announced yet: every planner receives every update from
        the first it announced on (a cell that joined late starts on the current one)."""
        numbers = {(r.producer, r.task): file_number(r.path) for mon in self.mons.values()
                   for r in mon.updates.records if r.producer is not None}
        updates = [(cell_producer(LEARNER, c), r["task"]) for c, res in self.results.items()
                   for r in res if r["update"] and r["update"]["status"] == SWAPPED]
        out = []
        for c in self.live_cells():
            recs = self.mons[c].updates.records
            first = min((file_number(r.path) for r in recs if r.producer is not None), default=0)
            out += [(c, p, t) for p, t in updates if numbers.get((p, t), first) >= first
                    and not any(rec.is_update(p, t) for rec in recs)]
        return out

    @property
    def status(self) -> int:
        if self.interrupted:
            return 130
        if self.bad_input:
            return BAD_INPUT
        if self.dead:
            return 1
        return UPDATE_FAILED if self.failed_updates else 0


def watch(w: FleetWatch, stop: Interrupt, env: dict[str, str], verbose: bool) -> None:
    """Spin the cells' monitors until every live cell is done or the user interrupts."""
    from .monitor_node import spin_once

    late = w.run.cells[-1] if w.run.join_after is not None else None
    while True:
        for mon in w.mons.values():
            spin_once(mon, 0.02)
        w.report()
        if late is not None and late not in w.started and w.swapped() >= w.run.join_after:
            print(f"peel fleet: {w.swapped()} updates swapped in; {late} joins", flush=True)
            w.start(late, env, verbose)
        w.check_children()
        if stop.signum is not None:
            print("peel fleet: interrupted; stopping the cells", file=sys.stderr, flush=True)
            w.interrupted = True
            return
        if w.finished() or not w.live_cells():
            return


def check_alone(mons: list[Any], wait_s: float) -> None:
    """Another peel graph on the domain (anything peel but this launcher's monitors)?"""
    from .monitor_node import spin_once

    own = {m.get_fully_qualified_name() for m in mons}
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        spin_once(mons[0], 0.1)
        found = [p for p in mons[0].peers() if p not in own]
        if found:
            domain = os.environ.get(discovery.DOMAIN_VAR) or "0"
            raise DomainTaken(f"ROS domain {domain} already holds a peel graph "
                              f"({', '.join(found[:4])}); start the fleet on a domain of its "
                              f"own: ROS_DOMAIN_ID=<0-101> (docs/runtime.md)")


def run_fleet(args: Any) -> int:
    """Start, watch and stop the fleet; returns the exit status."""
    run = resolve(args)
    learner, cells = children_of(run)
    env = child_env()
    discovery.confine()
    from .monitor_node import close_monitor, open_cell_monitors

    mons = open_cell_monitors({c: cell_producer(LEARNER, c) for c in run.cells})
    try:
        check_alone(mons, run.gp["graph.alone_wait_s"])
        run.out.create()
        run.run_dir.mkdir(parents=True, exist_ok=True)
        w = FleetWatch(run, learner, cells, dict(zip(run.cells, mons, strict=True)))
        stop = Interrupt()
        stop.install()
        try:
            learner[0].start(env, args.verbose)
            print(f"peel fleet: started {LEARNER_NODE} (pid {learner[0].pid})", flush=True)
            for cell in run.cells[:-1] if run.join_after is not None else run.cells:
                w.start(cell, env, args.verbose)
            watch(w, stop, env, args.verbose)
        finally:
            stop.restore()
            everyone = [c for kids in cells.values() for c in kids] + learner
            tear_down(everyone, run.gp["graph.stop_timeout_s"])
    finally:
        for mon in mons:
            close_monitor(mon)
    return write_summary(w)


def started_on(meta: dict[str, Any]) -> str | None:
    """The sha256 of the model a task started with, by the bridge's record of it in the
    trajectory's meta (None when the bridge had no record of that version)."""
    version = meta.get("model_version")
    return next((m.get("sha256") for m in meta.get("models") or []
                 if m.get("version") == version), None)


def write_summary(w: FleetWatch) -> int:
    """``summary.json``, the closing line and the summary as one JSON line; the exit status."""
    run = w.run
    cells = {}
    for cell, mon in w.mons.items():
        c = run.cells.index(cell)
        cells[cell] = {
            "seed": cell_seed(run.seed, c), "controller": run.controller(c),
            "dead": cell in w.dead,
            "results": w.results.get(cell, []),
            "models": [{"version": r.version, "sha256": r.sha256, "producer": r.producer,
                        "task": r.task} for r in mon.updates.records],
        }
    summary = {"cells": cells, "tasks": run.tasks, "plant": run.plant, "seed": run.seed,
               "learner_update_s": update_times(w.learner[0].log),
               "dead": w.dead, "failed_updates": w.failed_updates, "status": w.status,
               "run_dir": str(run.run_dir), "bag": str(run.bag) if run.bag else None}
    atomic_write_text(run.run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    done = ", ".join(f"{c} {len(w.results.get(c, []))}/{run.tasks}"
                     + (" (dead)" if c in w.dead else "") for c in run.cells)
    print(f"peel fleet: tasks finished: {done}; run directory {run.run_dir}", flush=True)
    if w.dead:
        print(f"peel fleet: error: dead: {', '.join(w.dead)}", file=sys.stderr, flush=True)
    print(json.dumps(summary, sort_keys=True), flush=True)
    return w.status


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel fleet``; returns the exit status."""
    return run_fleet(_parser().parse_args(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(run_main("peel fleet", main))
