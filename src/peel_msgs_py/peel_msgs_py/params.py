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
"""

from __future__ import annotations

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

    def check(self, value: Any) -> Any:
        """Return ``value`` coerced to this spec's type, or raise ParameterError naming it."""
        if self.type is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if self.type is list and isinstance(value, tuple):
            value = list(value)
        if not isinstance(value, self.type) or (self.type is not bool and isinstance(value, bool)):
            raise ParameterError(
                f"parameter '{self.name}' must be of type {self.type.__name__}, "
                f"got {type(value).__name__} ({value!r})"
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
    without a leading slash) override them.
    """
    path = Path(path)
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
    if doc is None:
        return {}
    if not isinstance(doc, Mapping):
        raise PeelError(f"parameter file {path} must map node names to ros__parameters")
    merged: dict[str, Any] = {}
    for key in ("/**", node_name, "/" + node_name.lstrip("/")):
        section = doc.get(key)
        if section is None:
            continue
        if not isinstance(section, Mapping) or "ros__parameters" not in section:
            raise PeelError(f"parameter file {path}: section '{key}' has no ros__parameters")
        params = section["ros__parameters"] or {}
        if not isinstance(params, Mapping):
            raise PeelError(f"parameter file {path}: '{key}.ros__parameters' must be a mapping")
        merged.update(flatten(params))
    for name, value in merged.items():
        if not isinstance(value, _ALLOWED) and value is not None:
            raise ParameterError(
                f"parameter '{name}' in {path} has unsupported type {type(value).__name__}"
            )
    return merged


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
