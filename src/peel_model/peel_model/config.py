"""Typed configuration of the forward model f_theta (3.1): its architecture hyper-parameters.

The values live in ``config/model_learner_node.yaml`` (group ``model.*``; the learner node declares
them with its other groups, :mod:`model_learner_node.parameters`); other groups in that file are
ignored here. Every value is checked by :func:`peel_msgs_py.params.validate` against the
:data:`MODEL_SPECS` below, whose defaults mirror the shipped YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from typing import Any

from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.params import ParamSpec, load_node_params, validate_group

NODE = "model_learner_node"
ARCHS: tuple[str, ...] = ("ours", "mlp", "cnn-lstm")

MODEL_SPECS: list[ParamSpec] = [
    ParamSpec("model.arch", str, "ours", "architecture (3.1 / 4.3)", choices=ARCHS),
    ParamSpec("model.h", int, 10, "history length h (Eq. 2), samples", min=4, max=200),
    ParamSpec("model.conv_channels", int, 16, "channels per kernel (Eq. 7)", min=1, max=512),
    ParamSpec("model.kernels", list, [2, 4, 6], "kernel widths (3.1.1)"),
    ParamSpec("model.paddings", list, [0, 1, 2], "kernel paddings (3.1.1)"),
    ParamSpec("model.cnn_lstm_kernels", list, [4, 4, 4], "CNN-LSTM kernel widths (4.3)"),
    ParamSpec("model.cnn_lstm_paddings", list, [1, 1, 1], "CNN-LSTM paddings (4.3)"),
    ParamSpec("model.attention_hidden", int, 16, "attention MLP width (Eq. 8)", min=1, max=1024),
    ParamSpec("model.lstm_hidden", int, 32, "LSTM state size (Eq. 11-16)", min=1, max=1024),
    ParamSpec("model.fc", list, [128, 64, 32, 16], "regressor widths (3.1.3)"),
]

def _int_list(name: str, value: list, *, min_value: int) -> tuple[int, ...]:
    if not value or not all(isinstance(x, int) and not isinstance(x, bool) for x in value):
        raise ParameterError(f"parameter '{name}' must be a non-empty list of integers")
    if any(x < min_value for x in value):
        raise ParameterError(f"parameter '{name}' entries must be >= {min_value}, got {value}")
    return tuple(int(x) for x in value)


@dataclass(frozen=True)
class ModelConfig:
    """Architecture hyper-parameters (3.1). ``kernels``/``paddings`` are the multi-scale set."""

    arch: str = "ours"
    h: int = 10
    conv_channels: int = 16
    kernels: tuple[int, ...] = (2, 4, 6)
    paddings: tuple[int, ...] = (0, 1, 2)
    cnn_lstm_kernels: tuple[int, ...] = (4, 4, 4)
    cnn_lstm_paddings: tuple[int, ...] = (1, 1, 1)
    attention_hidden: int = 16
    lstm_hidden: int = 32
    fc: tuple[int, ...] = (128, 64, 32, 16)

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> ModelConfig:
        """Validate the ``model.*`` entries of a flat parameter dict."""
        p = validate_group(MODEL_SPECS, flat, "model")
        cfg = cls(
            arch=p["model.arch"],
            h=p["model.h"],
            conv_channels=p["model.conv_channels"],
            kernels=_int_list("model.kernels", p["model.kernels"], min_value=1),
            paddings=_int_list("model.paddings", p["model.paddings"], min_value=0),
            cnn_lstm_kernels=_int_list("model.cnn_lstm_kernels", p["model.cnn_lstm_kernels"],
                                       min_value=1),
            cnn_lstm_paddings=_int_list("model.cnn_lstm_paddings", p["model.cnn_lstm_paddings"],
                                        min_value=0),
            attention_hidden=p["model.attention_hidden"],
            lstm_hidden=p["model.lstm_hidden"],
            fc=_int_list("model.fc", p["model.fc"], min_value=1),
        )
        cfg.check()
        return cfg

    def check(self) -> None:
        """Raise ParameterError unless the kernels give equal-length outputs (3.1.1)."""
        if self.arch not in ARCHS:
            raise ParameterError(f"parameter 'model.arch' = {self.arch!r} is not one of {ARCHS}")
        for kname, pname in (("kernels", "paddings"), ("cnn_lstm_kernels", "cnn_lstm_paddings")):
            ks, ps = getattr(self, kname), getattr(self, pname)
            if len(ks) != len(ps):
                raise ParameterError(f"parameter 'model.{pname}' must have one entry per kernel")
            lengths = {self.h + 2 * p - k + 1 for k, p in zip(ks, ps, strict=True)}
            if len(lengths) != 1 or min(lengths) < 1:
                raise ParameterError(
                    f"parameter 'model.{kname}'/{pname} give unequal or empty conv outputs "
                    f"for h={self.h}: lengths {sorted(lengths)}"
                )

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ModelConfig:
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        cfg = cls(**kw)
        cfg.check()
        return cfg

    def with_arch(self, arch: str) -> ModelConfig:
        cfg = replace(self, arch=arch)
        cfg.check()
        return cfg


def load_params(overrides: str | None = None) -> dict[str, Any]:
    """Flat parameters of this node from the shipped YAML (+ optional override file)."""
    try:
        return load_node_params(NODE, overrides)
    except PeelError:
        if overrides is not None:
            raise
        return {}


def load_model_config(overrides: str | None = None) -> ModelConfig:
    """:class:`ModelConfig` from ``config/model_learner_node.yaml``."""
    return ModelConfig.from_params(load_params(overrides))
