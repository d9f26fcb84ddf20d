"""ROS 2 parameter YAML files: locating, loading, flattening and validating them.

Every paper constant lives in ``config/<node>.yaml`` in the ROS 2 parameter file layout::

    peel_sim_node:            # node name, or /** for every node
      ros__parameters:
        task:
          q_ter_mm: 25.0      # goal position q_ter (section 4.1)

Nested keys flatten to dotted parameter names (``task.q_ter_mm``), exactly as ``ros2 run ...
--ros-args --params-file`` does. Libraries declare what they read as :class:`ParamSpec` lists and
validate a flat dict with :func:`validate`; a wrong-typed or out-of-range value raises
:class:`~peel_msgs_py.errors.ParameterError` naming the parameter. Nothing here imports ROS.

Typing follows rclpy's static parameter typing: a parameter's type is its default's, so an
integer is refused for a DOUBLE parameter (``mppi.lambda: 1`` -- write ``1.0``), exactly as a
node refuses it on a robot (docs/runtime.md, "Parameters").

Unknown names are refused too, by every node and command that reads a parameter file: each
package registers the parameters its node declares under the entry-point group
``peel.parameters`` (``<node name> = <module>:<specs>``); :func:`load_param_file` refuses a
section that names no registered node (nor ``/**``), a name in a node's section that the node
does not declare, and a ``/**`` name that no node declares.
"""

from __future__ import annotations

import functools
import math
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from .errors import ParameterError, PeelError

#: Python types a parameter may have, as ROS 2 parameter types.
_ALLOWED = (bool, int, float, str, list)


@dataclass(frozen=True)
class ParamSpec:
    """A declared parameter: name, type, default, documented range and paper reference."""

    name: str
    type: type
    default: Any
    description: str = ""
    min: float | None = None
    max: float | None = None
    choices: Sequence[Any] | None = None
    #: Whether a running node accepts a new value (``set_parameters``); read-only otherwise.
    dynamic: bool = False

    @property
    def ros_type(self) -> str:
        """The ROS 2 parameter type name (``DOUBLE``, ``INTEGER_ARRAY``, ...)."""
        return ros_type_name(self.default if self.type is list else self.type())

    def check(self, value: Any) -> Any:
        """Return ``value`` if it fits this spec, else raise ParameterError naming the parameter.

        Types as rclpy checks them: no integer for a DOUBLE, no bool for an INTEGER; a list must
        hold one element type (that of the default; a list of floats refuses integers too).
        """
        if self.type is list and isinstance(value, tuple):
            value = list(value)
        got, want = ros_type_name(value), self.ros_type
        if got != want and not (self.type is list and isinstance(value, list) and not value):
            raise ParameterError(
                f"parameter '{self.name}': wrong type, expected {want} got {got} ({value!r})"
                + (" (write a float, e.g. 1.0)" if want == "DOUBLE" and got == "INTEGER" else "")
            )
        if isinstance(value, float) and not math.isfinite(value):
            raise ParameterError(f"parameter '{self.name}' must be finite, got {value!r}")
        if self.min is not None and value < self.min:
            raise ParameterError(f"parameter '{self.name}' = {value!r} is below its minimum {self.min}")
        if self.max is not None and value > self.max:
            raise ParameterError(f"parameter '{self.name}' = {value!r} is above its maximum {self.max}")
        if self.choices is not None and value not in self.choices:
            raise ParameterError(
                f"parameter '{self.name}' = {value!r} is not one of {list(self.choices)}"
            )
        return value


_SCALAR_TYPES = ((bool, "BOOL"), (int, "INTEGER"), (float, "DOUBLE"), (str, "STRING"))


def ros_type_name(value: Any) -> str:
    """ROS 2 parameter type of a Python value, as rclpy names it (``Parameter.Type``)."""
    for typ, name in _SCALAR_TYPES:
        if isinstance(value, typ):
            return name
    if isinstance(value, (list, tuple)):
        kinds = {ros_type_name(v) for v in value}
        if len(kinds) == 1 and next(iter(kinds)) in ("BOOL", "INTEGER", "DOUBLE", "STRING"):
            return f"{next(iter(kinds))}_ARRAY"
        return "BYTE_ARRAY" if not value else "MIXED_ARRAY"
    return "NOT_SET" if value is None else type(value).__name__


#: ``use_sim_time``, which rclpy declares on every node; listed so parameter files may set it.
USE_SIM_TIME = ParamSpec("use_sim_time", bool, False,
                         "ROS time from /clock (the simulator's) instead of the system clock",
                         dynamic=True)


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Flatten nested mappings to dotted names, as ROS 2 does for ``ros__parameters``."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten(value, name))
        else:
            out[name] = value
    return out


def load_param_file(path: str | os.PathLike[str], node_name: str) -> dict[str, Any]:
    """Load the flat parameter dict for ``node_name`` from a ROS 2 parameter YAML file.

    Entries under ``/**`` apply to every node; entries under the node's own name (with or
    without a leading slash) override them. Unknown sections and names are refused
    (:func:`check_names`).
    """
    path = Path(path)
    doc = _read_yaml(path)
    node_specs(node_name)  # the node's own registry first: /** names are looked up there
    sections: dict[str, dict[str, Any]] = {}
    for key, section in doc.items():
        if not isinstance(section, Mapping) or "ros__parameters" not in section:
            raise PeelError(f"parameter file {path}: section '{key}' has no ros__parameters")
        params = section["ros__parameters"] or {}
        if not isinstance(params, Mapping):
            raise PeelError(f"parameter file {path}: '{key}.ros__parameters' must be a mapping")
        sections[str(key)] = flatten(params)
    check_names(sections, path)
    merged: dict[str, Any] = {}
    for key in ("/**", node_name.lstrip("/"), "/" + node_name.lstrip("/")):
        merged.update(sections.get(key, {}))
    for name, value in merged.items():
        if not isinstance(value, _ALLOWED) and value is not None:
            raise ParameterError(
                f"parameter '{name}' in {path} has unsupported type {type(value).__name__}"
            )
    return merged


def node_sections(path: str | os.PathLike[str]) -> list[str]:
    """The node names a parameter file has sections for, ``/**`` left out, leading ``/`` dropped.

    A command that reads one node's parameters from a file uses this to refuse a file written
    for another node, whose entries :func:`load_param_file` would pass over without a word.
    """
    return sorted({str(k).lstrip("/") for k in _read_yaml(Path(path)) if str(k) != "/**"})


def _read_yaml(path: Path) -> Mapping[str, Any]:
    if path.is_dir():
        raise PeelError(f"parameter file {path} is a directory, not a file")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise PeelError(f"cannot read parameter file {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise PeelError(f"parameter file {path} is not valid UTF-8 (byte 0x{exc.object[exc.start]:02x} "
                        f"at offset {exc.start})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise PeelError(f"malformed YAML in parameter file {path}{where}") from None
    if doc is None:  # empty, or comments only: a file that sets nothing is a mistake
        raise PeelError(f"parameter file {path} is empty: it names no node (write e.g. "
                        f"'peel_planner_node: {{ros__parameters: {{...}}}}')")
    if not isinstance(doc, Mapping):
        raise PeelError(f"parameter file {path} must map node names to ros__parameters")
    return doc


#: Entry-point group under which each package registers its node's parameter specs.
ENTRY_POINT_GROUP = "peel.parameters"
_registry: dict[str, tuple[ParamSpec, ...]] | None = None


@functools.cache
def registered_nodes() -> dict[str, Any]:
    """Node name -> entry point of the ``peel.parameters`` group (nothing imported yet)."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def node_specs(node_name: str) -> tuple[ParamSpec, ...] | None:
    """Every parameter ``node_name`` declares (its registered specs); None if not registered."""
    global _registry
    if _registry is None:
        _registry = {}
    name = node_name.lstrip("/")
    if name not in _registry:
        ep = registered_nodes().get(name)
        if ep is None:
            return None
        _registry[name] = tuple(ep.load())
    return _registry[name]


def check_names(sections: Mapping[str, Mapping[str, Any]], source: str | os.PathLike[str]
                ) -> None:
    """Refuse a section that names no registered node, and names no node declares.

    ``sections`` maps a section key (``/**``, a node name) to its flat parameters. A name in a
    node's section must be one that node declares; a ``/**`` name one that some node declares.
    Without any registered node (packages not installed) nothing is checked.
    """
    nodes = registered_nodes()
    if not nodes:
        return
    for key, names in sections.items():
        if key == "/**":
            continue
        if key.lstrip("/") not in nodes:
            raise ParameterError(
                f"unknown node section '{key}' in {source} (known: /**, {', '.join(sorted(nodes))})")
        known = {s.name for s in node_specs(key) or ()}
        for name in names:
            if name not in known:
                raise ParameterError(f"unknown parameter '{name}' for {key.lstrip('/')} in {source}")
    # /** names: look in the registries already loaded first (no needless imports)
    left = set(sections.get("/**", {}))
    for node in sorted(nodes, key=lambda n: (_registry is None or n not in _registry, n)):
        if not left:
            break
        left -= {s.name for s in node_specs(node) or ()}
    if left:
        raise ParameterError(f"unknown parameter '{sorted(left)[0]}' under /** in {source} "
                             "(no peel node declares it)")


def ros_args_overrides(argv: Sequence[str], node_name: str) -> dict[str, Any]:
    """The parameter overrides ``argv``'s ``--ros-args`` give ``node_name``, checked by name.

    ``--params-file FILE`` (read with :func:`load_param_file`: unknown sections and names are
    refused) and ``-p``/``--param [node:]name:=value`` (value parsed as YAML, as rcl does; a
    name the node does not declare is refused). Later arguments win, as in rcl. Types and
    ranges are left to the node's declaration (rclpy), which names the parameter too.
    """
    args = list(argv)
    out: dict[str, Any] = {}
    in_ros = False
    known = {s.name for s in node_specs(node_name) or ()}
    i = 0
    while i < len(args):
        arg = args[i]
        i += 1
        if arg == "--ros-args":
            in_ros = True
            continue
        if arg == "--" or not in_ros:
            in_ros = False if arg == "--" else in_ros
            continue
        if arg == "--params-file" and i < len(args):
            out.update(load_param_file(args[i], node_name))
            i += 1
        elif arg in ("-p", "--param") and i < len(args):
            target, _, value = args[i].partition(":=")
            i += 1
            node, _, name = target.rpartition(":")
            if node and node.lstrip("/") != node_name.lstrip("/"):
                continue
            if known and name not in known:
                raise ParameterError(f"unknown parameter '{name}' for {node_name} (-p {target})")
            try:
                out[name] = yaml.safe_load(value) if value else ""
            except yaml.YAMLError:
                out[name] = value
    return out


def validate(
    specs: Iterable[ParamSpec], values: Mapping[str, Any], *, allow_unknown: bool = False
) -> dict[str, Any]:
    """Defaults from ``specs`` overridden by ``values``, each checked; returns the flat dict."""
    specs = list(specs)
    known = {s.name: s for s in specs}
    if not allow_unknown:
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ParameterError(f"unknown parameter '{unknown[0]}'")
    out: dict[str, Any] = {}
    for spec in specs:
        out[spec.name] = spec.check(values.get(spec.name, spec.default))
    return out


def validate_group(
    specs: Iterable[ParamSpec], flat: Mapping[str, Any], group: str, *, strip: bool = False
) -> dict[str, Any]:
    """:func:`validate` the ``<group>.*`` entries of a flat dict (other keys are ignored).

    With ``strip=True`` the result is keyed by the names inside the group (``lr`` rather than
    ``train.lr``), ready for ``SomeConfig(**values)``.
    """
    prefix = group + "."
    values = validate(specs, {k: v for k, v in flat.items() if k.startswith(prefix)})
    return {k[len(prefix):]: v for k, v in values.items()} if strip else values


def config_dir() -> Path:
    """The directory holding the shipped ``config/*.yaml`` files.

    Order: ``$PEEL_CONFIG_DIR``; the source tree (editable installs and a checkout);
    ``share/peel_bringup/config`` of an ament or pip install prefix.
    """
    env = os.environ.get("PEEL_CONFIG_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        cand = parent / "config"
        if (cand / "peel_sim_node.yaml").is_file():
            return cand
    prefixes = [Path(sys.prefix)]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            prefixes.append(Path(prefix))
    for prefix in prefixes:
        cand = prefix / "share" / "peel_bringup" / "config"
        if cand.is_dir():
            return cand
    raise PeelError("cannot find peel's config/ directory; set PEEL_CONFIG_DIR")


def default_param_file(node_name: str) -> Path:
    """``config/<node_name>.yaml``."""
    return config_dir() / f"{node_name}.yaml"


def load_node_params(
    node_name: str, overrides: str | os.PathLike[str] | None = None
) -> dict[str, Any]:
    """Shipped parameters of ``node_name``, with an optional override file applied on top."""
    values = load_param_file(default_param_file(node_name), node_name)
    if overrides is not None:
        values.update(load_param_file(overrides, node_name))
    return values
