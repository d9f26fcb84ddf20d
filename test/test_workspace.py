"""The workspace itself: ament_python packages, the `peel` command, one-way dependencies.

Dependencies are read from the sources with :mod:`ast` (nothing is imported): every import
statement counts, a lazy one inside a function as much as one at the top of a module.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The packages in layers, lowest first: a package imports only packages of lower layers
#: (never one of its own layer or a higher one).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("peel_msgs_py",),  # interfaces: topics, QoS, codec, units, params, rclpy helpers
    ("peel_model", "peel_bag", "peel_bridge"),
    ("peel_sim_node", "peel_nachi_bridge"),  # the plant bridges, on peel_bridge's core
    ("peel_nachi_emulator", "model_learner_node", "peel_planner_node", "peel_residual"),
    ("peel_experiments",),
    ("peel_bringup",),  # the graph, the demo, the launch file, the `peel` command
)
PACKAGES = [pkg for layer in LAYERS for pkg in layer]
LAYER_OF = {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}
#: Allowed imports between our packages (each a subset of the lower layers).
ALLOWED = {
    "peel_msgs_py": set(),
    "peel_model": {"peel_msgs_py"},
    "peel_bag": {"peel_msgs_py"},
    "peel_bridge": {"peel_msgs_py"},
    "peel_sim_node": {"peel_msgs_py", "peel_bridge"},
    "peel_nachi_bridge": {"peel_msgs_py", "peel_bridge"},  # runs next to a real controller: no simulator
    "peel_nachi_emulator": {"peel_msgs_py", "peel_sim_node", "peel_nachi_bridge"},  # the plant it runs
    "model_learner_node": {"peel_msgs_py", "peel_model", "peel_bag", "peel_sim_node"},  # peel train's readers
    "peel_planner_node": {"peel_msgs_py", "peel_model"},
    "peel_residual": {"peel_msgs_py", "peel_model", "peel_bag"},
    "peel_experiments": {p for p in PACKAGES if LAYER_OF[p] < LAYER_OF["peel_experiments"]},
    "peel_bringup": {p for p in PACKAGES if LAYER_OF[p] < LAYER_OF["peel_bringup"]},
}
ROS_MODULES = {"rclpy", "geometry_msgs", "std_msgs", "rosgraph_msgs", "rcl_interfaces",
               "builtin_interfaces", "std_srvs", "diagnostic_msgs", "launch", "launch_ros",
               "ament_index_python"}


def test_layers_hold_every_package() -> None:
    assert sorted(PACKAGES) == sorted(p.name for p in (ROOT / "src").iterdir() if (p / "package.xml").is_file())
    assert set(ALLOWED) == set(PACKAGES)
    for pkg, allowed in ALLOWED.items():
        assert all(LAYER_OF[dep] < LAYER_OF[pkg] for dep in allowed), pkg


@pytest.mark.parametrize("pkg", PACKAGES)
def test_package_is_ament_python(pkg: str) -> None:
    base = ROOT / "src" / pkg
    root = ET.parse(base / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == pkg
    assert root.find("export/build_type").text == "ament_python"
    assert (base / "resource" / pkg).is_file()
    assert (base / "setup.cfg").is_file()
    assert (base / pkg / "__init__.py").is_file()
    setup = (base / "setup.py").read_text()
    assert f'package_name = "{pkg}"' in setup


# ------------------------------------------------------------------------ the import graph (ast)
def _module_name(path: Path) -> str:
    """``src/<pkg>/<pkg>/a/b.py`` -> ``<pkg>.a.b`` (a package's ``__init__.py`` -> the package)."""
    parts = list(path.relative_to(ROOT / "src").with_suffix("").parts[1:])
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def _modules() -> dict[str, Path]:
    """Every module of every package, by dotted name."""
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / "src" / pkg / pkg).rglob("*.py")}


def _known(name: str) -> str | None:
    """``name`` or its longest prefix that is one of our modules."""
    modules = _modules()
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _targets(module: str, node: ast.Import | ast.ImportFrom) -> set[str]:
    """The modules of ours one import statement of ``module`` loads (lazy or not)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            here = module.split(".") if _modules()[module].name == "__init__.py" else module.split(".")[:-1]
            base = ".".join([*here[: len(here) - node.level + 1], *([node.module] if node.module else [])])
        names = [f"{base}.{alias.name}" if _known(f"{base}.{alias.name}") == f"{base}.{alias.name}" else base
                 for alias in node.names]
    return {t for t in map(_known, names) if t is not None and t != module}


@cache
def _graph() -> dict[str, set[str]]:
    """Module -> the modules of ours it imports, and the packages above them that load first."""
    graph: dict[str, set[str]] = {}
    for module, path in _modules().items():
        out: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in _targets(module, node):
                    parts = target.split(".")
                    out.update(".".join(parts[:i]) for i in range(1, len(parts) + 1)
                               if not module.startswith(".".join(parts[:i]) + "."))
        graph[module] = out - {module}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _package_imports(pkg: str) -> dict[str, set[str]]:
    """Other packages of ours that ``pkg``'s modules import: package -> importing modules."""
    out: dict[str, set[str]] = {}
    for module, targets in _graph().items():
        if module.split(".")[0] == pkg:
            for target in targets:
                if target.split(".")[0] != pkg:
                    out.setdefault(target.split(".")[0], set()).add(module)
    return out


def test_no_import_circle() -> None:
    """No modules import each other in a loop, counting the lazy imports inside functions."""
    circles = _circles(_graph())
    assert not circles, f"import circles (lazy imports included): {circles}"


def test_circle_finder_finds_a_lazy_circle() -> None:
    """The check above sees a circle closed by a function-level import."""
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("pkg", PACKAGES)
def test_dependencies_point_one_way(pkg: str) -> None:
    for dep, modules in _package_imports(pkg).items():
        assert dep in ALLOWED[pkg], f"{sorted(modules)} import {dep} against the dependency direction"
        assert LAYER_OF[dep] < LAYER_OF[pkg], f"{sorted(modules)} import the higher {dep}"


def test_named_rules() -> None:
    """The rules the architecture rests on, spelled out (each implied by ALLOWED too)."""
    assert "model_learner_node" not in _package_imports("peel_planner_node")
    nachi = _package_imports("peel_nachi_bridge")
    assert "peel_sim_node" not in nachi and "peel_nachi_emulator" not in nachi
    assert _package_imports("peel_msgs_py") == {}


def _manifest_deps(pkg: str) -> set[str]:
    root = ET.parse(ROOT / "src" / pkg / "package.xml").getroot()
    return {e.text or "" for tag in ("depend", "exec_depend") for e in root.iter(tag)} & set(PACKAGES)


@pytest.mark.parametrize("pkg", PACKAGES)
def test_manifest_declares_our_packages_it_imports(pkg: str) -> None:
    imported = set(_package_imports(pkg))
    assert imported <= _manifest_deps(pkg), f"{pkg}/package.xml lacks {imported - _manifest_deps(pkg)}"
    assert _manifest_deps(pkg) <= ALLOWED[pkg], f"{pkg}/package.xml declares {_manifest_deps(pkg) - ALLOWED[pkg]}"


def test_setup_installs_every_package_after_its_dependencies() -> None:
    text = (ROOT / "scripts" / "setup.sh").read_text()
    order = re.search(r"^PACKAGES=\(([^)]*)\)", text, re.M).group(1).split()
    assert sorted(order) == sorted(PACKAGES)
    for i, pkg in enumerate(order):
        assert _manifest_deps(pkg) <= set(order[:i]), f"setup.sh installs {pkg} before its dependencies"


def test_libraries_import_no_ros() -> None:
    """Only node modules (``*node.py``) and ``peel_msgs_py.ros`` may touch ROS modules."""
    for pkg in PACKAGES:
        for path in (ROOT / "src" / pkg / pkg).rglob("*.py"):
            rel = path.relative_to(ROOT / "src" / pkg / pkg)
            if (pkg, rel.parts[0]) == ("peel_msgs_py", "ros") or path.name.endswith("node.py"):
                continue
            bad = _imports(path) & ROS_MODULES
            assert not bad, f"library module {path.relative_to(ROOT)} imports ROS: {bad}"


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


# ------------------------------------------------------------------------------ the peel command
def _peel(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", *args],
                          capture_output=True, text=True, timeout=120)


def test_peel_help_lists_subcommands() -> None:
    out = _peel("--help")
    assert out.returncode == 0
    for name in ("dataset", "train", "bench", "experiment", "graph", "demo", "nachi-emulator", "record",
                 "soak", "residual", "figures"):
        assert f"  {name}" in out.stdout


def test_every_subcommand_and_bench_target_resolves() -> None:
    """Each ``module:function`` the dispatchers name exists where they say (no import needed)."""
    from peel_bringup.cli import SUBCOMMANDS
    from peel_experiments.bench import TARGETS

    for spec in [s for s, _ in SUBCOMMANDS.values()] + [s for s, _ in TARGETS.values()]:
        module, func = spec.split(":")
        path = _modules().get(module)
        assert path is not None, f"{spec}: no module {module}"
        defined = {n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}
        assert func in defined, f"{spec}: {module} defines no {func}()"


def test_unknown_command_is_one_line_error() -> None:
    out = _peel("frobnicate")
    assert out.returncode == 2
    assert out.stderr.startswith("peel: error: unknown command 'frobnicate'")
    assert "Traceback" not in out.stderr


def test_unknown_bench_target_is_one_line_error() -> None:
    out = _peel("bench", "warp-drive")
    assert out.returncode == 2
    assert "unknown benchmark 'warp-drive'" in out.stderr
    assert "Traceback" not in out.stderr


def test_the_embedded_runtime_is_retired() -> None:
    """rclpy is the one runtime: no module, test, requirement or setup step names the embedded
    Cyclone DDS runtime any more."""
    assert not (ROOT / "src" / "peel_msgs_py" / "peel_msgs_py" / "runtime").exists()
    retired = ("peel_msgs_py.runtime", "PEEL_RUNTIME", "cyclonedds")
    files = [*(ROOT / "src").rglob("*.py"), *(ROOT / "test").glob("*.py"),
             *ROOT.glob("requirements*.txt"), ROOT / "scripts" / "setup.sh"]
    for path in files:
        if path.name == Path(__file__).name:
            continue
        text = path.read_text()
        for word in retired:
            assert word not in text, f"{path.relative_to(ROOT)} names {word}"
    reqs = (ROOT / "requirements-ros.txt").read_text()
    for pin in ("ros-rclpy==7.1.6", "ros-rcl-interfaces==2.0.3", "ros-geometry-msgs==5.3.6",
                "ros-std-msgs==5.3.6", "ros-std-srvs==5.3.6", "ros-rosgraph-msgs==2.0.3",
                "ros-rmw-fastrtps-cpp==8.4.3"):
        assert pin in reqs.splitlines(), pin
    assert all(line.startswith("#") or "==" in line for line in reqs.splitlines() if line)
