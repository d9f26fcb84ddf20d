"""Checkpoints of the forward model: ``<name>.safetensors`` + ``<name>.json`` (never a pickle).

The safetensors file holds every parameter and normalisation buffer of a
:class:`~peel_model.predictor.ForcePredictor`; the JSON beside it holds what is needed to
rebuild and check it: format name and version, architecture and its hyper-parameters (h, ...),
the normalisation in readable form, units, one entry per tensor (shape, dtype), the size and
SHA-256 of the safetensors file, and free ``meta`` (dataset hash, metrics, training settings).

A model with a compensation term (:class:`~peel_model.compensated.CompensatedPredictor`,
written by ``peel residual``) is the same pair: the safetensors file holds f_theta exactly as a
plain checkpoint does, the JSON has ``format_version`` 2 and a ``compensation`` block with the
named physical terms and their coefficients. The same block is sealed into the safetensors
header's metadata (``compensation``, canonical JSON), so the file's SHA-256 -- the model's
identity for the planner's versions (:mod:`~peel_model.versions`) -- covers the terms
too, and a JSON whose terms were edited is refused. The terms' formulas come from
:mod:`~peel_model.effect_terms` by family name; nothing in the file is executed. A reader
of version 1 refuses such a file instead of silently dropping the terms.

:func:`load_checkpoint` is strict: it refuses a missing or malformed JSON, another format or
version, an unknown architecture, a safetensors file of the wrong size (truncated) or checksum,
one that does not parse, and any tensor whose name, shape or dtype differs from the JSON or from
the network the JSON describes, each with a :class:`CheckpointError` saying which and why. Both
files are written atomically (temporary file + ``os.replace``); save then load is bit-exact.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from peel_msgs_py.atomic import atomic_write_bytes
from peel_msgs_py.errors import CheckpointError, PeelError

from .compensated import CompensatedPredictor
from .config import ARCHS, ModelConfig
from .predictor import ForcePredictor

FORMAT = "peel-forward-model"
FORMAT_VERSION = 1
#: format_version of a checkpoint with a ``compensation`` block (docs/residual.md).
COMPENSATED_VERSION = 2
CODE_VERSION = "0.1.0"
UNITS = {
    "hist_columns": ["q_mm", "v_mmps", "fx_N", "fz_N"],
    "v_next": "mm/s",
    "outputs": ["fx_N", "fz_N"],
    "dt_s": 0.1,
    "psi": "mm",
}
_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def checkpoint_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """(``.safetensors``, ``.json``) for a path given with either suffix or none."""
    p = Path(path)
    if p.suffix in (".safetensors", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".safetensors"), p.with_name(p.name + ".json")


def jsonable(obj: Any) -> Any:
    """``obj`` with NaN/inf floats replaced by None (strict JSON), tuples as lists."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return jsonable(obj.item())
    return obj


def atomic_write_json(path: Path, obj: Any) -> None:
    """Strict JSON (no NaN), written atomically."""
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False) + "\n"
    atomic_write_bytes(path, text.encode())


def _dtype_name(dtype: torch.dtype) -> str:
    for name, dt in _DTYPES.items():
        if dt == dtype:
            return name
    raise CheckpointError(f"unsupported tensor dtype {dtype}")


def save_checkpoint(
    path: str | os.PathLike[str], predictor: ForcePredictor | CompensatedPredictor,
    meta: dict[str, Any] | None = None
) -> Path:
    """Write ``<name>.safetensors`` and ``<name>.json``; returns the safetensors path.

    A :class:`CompensatedPredictor` is saved as its f_theta plus the ``compensation`` block."""
    st_path, js_path = checkpoint_paths(path)
    compensation = None
    if isinstance(predictor, CompensatedPredictor):
        compensation = predictor.to_json()
        predictor = predictor.base
    version = FORMAT_VERSION if compensation is None else COMPENSATED_VERSION
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in predictor.state_dict().items()}
    header = {"format": FORMAT, "format_version": str(version)}
    if compensation is not None:
        compensation = jsonable(compensation)
        header["compensation"] = _canonical(compensation)
    blob = _sorted_header(st_save(tensors, metadata=header))
    config = {
        "format": FORMAT,
        "format_version": version,
        "code_version": CODE_VERSION,
        "arch": predictor.arch,
        "h": predictor.h,
        "model_config": predictor.cfg.to_json(),
        "normalization": predictor.normalization.to_json(),
        "units": UNITS,
        "tensors": {
            k: {"shape": list(v.shape), "dtype": _dtype_name(v.dtype)} for k, v in tensors.items()
        },
        "safetensors_bytes": len(blob),
        "safetensors_sha256": hashlib.sha256(blob).hexdigest(),
        "meta": meta or {},
    }
    if compensation is not None:
        config["compensation"] = compensation
    try:
        config = jsonable(config)
        json.dumps(config, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise PeelError(f"checkpoint meta is not JSON-serialisable: {exc}") from None
    atomic_write_bytes(st_path, blob)
    atomic_write_json(js_path, config)
    return st_path


def read_checkpoint_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The checked JSON config of a checkpoint (format, version, architecture)."""
    _, js_path = checkpoint_paths(path)
    try:
        text = js_path.read_text()
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint config {js_path}: {exc.strerror}") from None
    try:
        cfg = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"checkpoint config {js_path} is not valid JSON ({exc.msg} at "
                              f"line {exc.lineno}); truncated?") from None
    if not isinstance(cfg, dict):
        raise CheckpointError(f"checkpoint config {js_path} must be a JSON object")
    if cfg.get("format") != FORMAT:
        raise CheckpointError(
            f"checkpoint config {js_path}: format is {cfg.get('format')!r}, expected {FORMAT!r}"
        )
    if cfg.get("format_version") not in (FORMAT_VERSION, COMPENSATED_VERSION):
        raise CheckpointError(
            f"checkpoint config {js_path}: format_version {cfg.get('format_version')!r} is not "
            f"supported (this code reads versions {FORMAT_VERSION} and {COMPENSATED_VERSION})"
        )
    if (cfg.get("format_version") == COMPENSATED_VERSION) != ("compensation" in cfg):
        raise CheckpointError(
            f"checkpoint config {js_path}: format_version {COMPENSATED_VERSION} and a "
            "'compensation' block go together"
        )
    if cfg.get("arch") not in ARCHS:
        raise CheckpointError(
            f"checkpoint config {js_path}: arch {cfg.get('arch')!r} is not one of {ARCHS}"
        )
    for key in ("model_config", "tensors", "safetensors_sha256", "safetensors_bytes", "h"):
        if key not in cfg:
            raise CheckpointError(f"checkpoint config {js_path}: missing field {key!r}")
    return cfg


def load_checkpoint(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> ForcePredictor | CompensatedPredictor:
    """Rebuild a :class:`ForcePredictor` (or, for a ``compensation`` block, a
    :class:`CompensatedPredictor` around it) from a checkpoint, checking everything."""
    st_path, js_path = checkpoint_paths(path)
    cfg = read_checkpoint_config(js_path)
    try:
        mcfg = ModelConfig.from_json(cfg["model_config"])
    except (PeelError, TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint config {js_path}: bad model_config: {exc}") from None
    if mcfg.arch != cfg["arch"] or mcfg.h != cfg["h"]:
        raise CheckpointError(
            f"checkpoint config {js_path}: arch/h ({cfg['arch']}, {cfg['h']}) disagree with "
            f"model_config ({mcfg.arch}, {mcfg.h})"
        )
    try:
        blob = st_path.read_bytes()
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint weights {st_path}: {exc.strerror}") from None
    if len(blob) != cfg["safetensors_bytes"]:
        raise CheckpointError(
            f"checkpoint weights {st_path} have {len(blob)} bytes but its config records "
            f"{cfg['safetensors_bytes']}: truncated or not the file this config belongs to"
        )
    digest = hashlib.sha256(blob).hexdigest()
    if digest != cfg["safetensors_sha256"]:
        raise CheckpointError(
            f"checkpoint weights {st_path}: SHA-256 {digest[:12]}... does not match the config's "
            f"{str(cfg['safetensors_sha256'])[:12]}...: corrupted or mismatched files"
        )
    try:
        tensors = st_load(blob)
    except Exception as exc:  # safetensors raises its own error types
        raise CheckpointError(f"checkpoint weights {st_path} are not a valid safetensors file: "
                              f"{exc}") from None
    predictor = ForcePredictor(mcfg)
    expected = predictor.state_dict()
    recorded = cfg["tensors"]
    for where, names in (("the safetensors file", set(tensors)), ("the config", set(recorded))):
        missing = sorted(set(expected) - names)
        extra = sorted(names - set(expected))
        if missing or extra:
            what = f"missing {missing[:3]}" if missing else f"unexpected {extra[:3]}"
            raise CheckpointError(
                f"checkpoint {st_path}: {where} does not match a {mcfg.arch!r} model: {what}"
            )
    for name, ref in expected.items():
        t = tensors[name]
        rec = recorded[name]
        if list(t.shape) != list(rec.get("shape", [])) or _dtype_name(t.dtype) != rec.get("dtype"):
            raise CheckpointError(
                f"checkpoint {st_path}: tensor {name!r} is {_dtype_name(t.dtype)} "
                f"{list(t.shape)} but the config records {rec.get('dtype')} {rec.get('shape')}"
            )
        if t.shape != ref.shape or t.dtype != ref.dtype:
            raise CheckpointError(
                f"checkpoint {st_path}: tensor {name!r} has shape {list(t.shape)} "
                f"({_dtype_name(t.dtype)}) but a {mcfg.arch!r} model with h={mcfg.h} needs "
                f"{list(ref.shape)} ({_dtype_name(ref.dtype)})"
            )
        if not bool(torch.isfinite(t).all()):
            raise CheckpointError(f"checkpoint {st_path}: tensor {name!r} has non-finite values")
    predictor.load_state_dict(tensors, strict=True)
    if not math.isfinite(float(predictor.pad_compliance.item())):
        raise CheckpointError(f"checkpoint {st_path}: non-finite pad compliance")
    predictor.eval()
    if "compensation" in cfg:
        try:
            comp = CompensatedPredictor.from_json(predictor, cfg["compensation"])
        except PeelError as exc:
            raise CheckpointError(f"checkpoint config {js_path}: bad compensation: {exc}") from None
        if abs(comp.dt_s - float(cfg.get("units", {}).get("dt_s", comp.dt_s))) > 1e-9:
            raise CheckpointError(f"checkpoint config {js_path}: compensation dt_s {comp.dt_s:g} "
                                  "differs from the model's units dt_s")
        if _header_metadata(blob).get("compensation") != _canonical(cfg["compensation"]):
            raise CheckpointError(f"checkpoint config {js_path}: its compensation block differs "
                                  f"from the one sealed in {st_path.name}")
        return comp.eval().to(device)
    return predictor.to(device)


def _canonical(obj: Any) -> str:
    """One text per JSON value (sorted keys, no spaces): what the weights file seals."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _sorted_header(blob: bytes) -> bytes:
    """``blob`` with its JSON header written with sorted keys, so that the same tensors and
    metadata always give the same bytes and so the same SHA-256 (the model's identity):
    ``safetensors`` writes ``__metadata__`` in hash-map order, which changes from one save to
    the next. The header is padded with spaces to a multiple of 8 bytes as ``safetensors``
    pads it; tensor offsets count from the end of the header, so the data is unchanged."""
    n = int.from_bytes(blob[:8], "little")
    text = json.dumps(json.loads(blob[8:8 + n]), sort_keys=True, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return len(text).to_bytes(8, "little") + text + blob[8 + n:]


def _header_metadata(blob: bytes) -> dict[str, str]:
    """The ``__metadata__`` of a safetensors file's JSON header (8-byte length, then JSON)."""
    try:
        n = int.from_bytes(blob[:8], "little")
        meta = json.loads(blob[8:8 + n]).get("__metadata__") or {}
    except (ValueError, AttributeError):
        return {}
    return meta if isinstance(meta, dict) else {}


def shipped_checkpoint() -> Path:
    """Path of the committed pretrained ``ours`` model (``checkpoints/pretrained.safetensors``)."""
    path = Path(__file__).resolve().parent / "checkpoints" / "pretrained.safetensors"
    if not path.is_file() or not path.with_suffix(".json").is_file():
        raise CheckpointError(f"the shipped checkpoint is missing: {path} (+ .json)")
    return path
