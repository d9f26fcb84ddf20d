"""The fused rollout's view of the forward model: capability check, schedule, rearranged weights.

:func:`fused_support` is the one place that decides whether a predictor is a model the fused
rollout reproduces exactly (``ForcePredictor`` with a ``ConvAttentionLSTM`` body, i.e. the
``ours`` and ``cnn-lstm`` architectures, no subclass that changes ``predict``); any other model is
rolled out by the reference dynamics (``dynamics.learned_dynamics``).

:class:`Schedule` holds the wavefront geometry of a window of h rows (module docstring of
``fused.py``); :class:`FusedWeights` rearranges the predictor's weights for the fused ops and
rebuilds them whenever a parameter or buffer changes: the cache key is every tensor's
``(data_ptr, _version)``, and ``_version`` is bumped by every in-place update (``add_``,
``copy_``, ``load_state_dict``, an optimiser step), so MAML's in-place updates (Algorithm 1) are
seen.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn


def fused_support(predictor: Any) -> str | None:
    """None when the fused rollout computes ``predictor.predict`` exactly, else the reason why
    not. Exact types, not ``isinstance``: a subclass may change what ``predict`` computes."""
    try:
        from peel_model.model import LSTM, ConvAttentionLSTM, MultiScaleConv, ScaleAttention
        from peel_model.predictor import ForcePredictor
    except ImportError:  # pragma: no cover - the package is a declared dependency
        return "model_learner_node is not importable"
    if type(predictor) is not ForcePredictor:
        return f"model type {type(predictor).__name__} is not ForcePredictor"
    body = predictor.body
    parts = ((body, ConvAttentionLSTM), (body.conv if hasattr(body, "conv") else None,
                                          MultiScaleConv),
             (getattr(body, "attention", None), ScaleAttention), (getattr(body, "lstm", None), LSTM))
    for module, want in parts:
        if type(module) is not want:
            return f"architecture {predictor.arch!r}: no {want.__name__} where the fused " \
                   "rollout needs one"
    mlp = list(body.attention.mlp)
    if [type(m) for m in mlp] != [nn.Linear, nn.Tanh, nn.Linear]:
        return "attention MLP is not Linear-Tanh-Linear"
    reg = list(body.regressor)
    want = [nn.Linear, nn.ReLU] * (len(reg) // 2) + [nn.Linear]
    if [type(m) for m in reg] != want:
        return "regressor is not (Linear, ReLU)* Linear"
    convs = list(body.conv.convs)
    if any(c.stride != (1,) or c.dilation != (1,) or c.groups != 1 for c in convs):
        return "convolutions with stride, dilation or groups"
    sch = Schedule.of(predictor)
    if sch.width > sch.h:  # the wavefront needs an interior position P <= J
        return f"merged kernel width {sch.width} exceeds the history h = {sch.h}"
    return None


@dataclass(frozen=True)
class Schedule:
    """Wavefront geometry of the merged convolution over an h-row window (``fused.py``).

    The three kernels (widths k_i, paddings p_i) are one kernel of ``width`` = max(k_i + P -
    p_i) with padding ``pad`` = P = max(p_i); a window has ``length`` L = h + 2P - width + 1
    positions; positions P..J (``last_interior`` J = h + P - width) see only rows inside the
    window; ``depth`` D = J + 1 windows are in flight at each model step. ``wave`` lists the
    (window offset, position) pairs projected at each step: the top edges of the P newest
    windows (oldest first), window k's interior position J and its bottom edges.
    """

    h: int
    channels: int
    n_scales: int
    hidden: int
    pad: int
    width: int

    @classmethod
    def of(cls, predictor: Any) -> Schedule:
        body = predictor.body
        convs = list(body.conv.convs)
        pad = max(int(c.padding[0]) for c in convs)
        return cls(h=int(predictor.h), channels=convs[0].out_channels, n_scales=len(convs),
                   hidden=int(body.lstm.hidden), pad=pad,
                   width=max(int(c.kernel_size[0]) + pad - int(c.padding[0]) for c in convs))

    @property
    def length(self) -> int:
        return self.h + 2 * self.pad - self.width + 1

    @property
    def last_interior(self) -> int:
        return self.h + self.pad - self.width

    @property
    def depth(self) -> int:
        return self.last_interior + 1

    @property
    def conv_width(self) -> int:
        """Channels of all scales together (the weighted S of Eq. 10)."""
        return self.channels * self.n_scales

    @property
    def wave(self) -> list[tuple[int, int]]:
        j_int = self.last_interior
        return ([(j_int - j, j) for j in reversed(range(self.pad))]
                + [(0, j) for j in range(j_int, self.length)])

    @property
    def fresh(self) -> list[int]:
        """Window positions projected anew at a step (the others carry over from earlier)."""
        return [*range(self.pad), self.last_interior, *range(self.last_interior + 1, self.length)]


@dataclass(frozen=True)
class Weights:
    """The predictor's weights rearranged for the fused ops (gates in the order i, f, o, g; the
    g gate's rows doubled: tanh(g) = 2 sigmoid(2g) - 1)."""

    conv_wave: torch.Tensor       # [h*4, len(wave)*C]: the conv of the wavefront positions
    conv_wave_bias: torch.Tensor  # [len(wave)*C]
    conv_all: torch.Tensor        # [h*4, L*C]: the conv of every position (prologue)
    conv_all_bias: torch.Tensor   # [L*C]
    att1_weight_t: torch.Tensor   # attention MLP (Eq. 8), transposed, first layer doubled and
    att1_bias: torch.Tensor       # the second folded so that sigmoid replaces tanh (rearrange)
    att2_weight_t: torch.Tensor
    att2_bias: torch.Tensor
    att_shift: bool               # the softmax (Eq. 9) needs its max-shift
    scale_expand: torch.Tensor    # [n_scales, C] 0/1: each scale's weight over its channels
    wx_t: torch.Tensor            # W_x^T [C, 4 hid] (prologue)
    bx: torch.Tensor              # b of W_x x + b [4 hid] (prologue)
    wh_t: torch.Tensor            # W_h^T [hid, 4 hid] (prologue)
    wx_gates_aug: torch.Tensor    # [4, C + 1, hid]: W_x with b as its last row, gate-major
    wh_gates: torch.Tensor        # [4, hid, hid]: W_h gate-major
    fc1_h_t: torch.Tensor         # first FC layer, h_L part, transposed [hid, width1]
    fc1_v: torch.Tensor           # first FC layer, v_{k+1} column [width1]
    fc1_bias: torch.Tensor        # [width1]
    fc_layers: tuple[torch.Tensor, ...]  # later FC layers on [y, 1]: [in + 1, out], the last
    #                                      with the increment head's scale and shift folded in
    in_mean: torch.Tensor         # input normalisation [4]
    in_std: torch.Tensor


class FusedWeights:
    """The current :class:`Weights` of a predictor, rebuilt when it changes (module docstring)."""

    def __init__(self, predictor: Any, dtype: torch.dtype | None = None) -> None:
        self.predictor = predictor
        self.schedule = Schedule.of(predictor)
        self.dtype = dtype
        self.generation = 0  # bumped on every rebuild (workspaces bind the weight tensors)
        self._key: tuple | None = None
        self._weights: Weights | None = None
        # the modules' parameter/buffer dicts, found once (walking the module tree cost
        # ~0.3 ms per plan); reading the dicts each time still sees a replaced tensor
        self._slots = [(d, name) for m in predictor.modules()
                       for d in (m._parameters, m._buffers) for name in d]

    def _version(self) -> tuple:
        return tuple((t.data_ptr(), t._version, t.dtype, t.device)
                     for d, name in self._slots if (t := d[name]) is not None)

    def current(self) -> Weights:
        """The weights of the predictor as it is now (cached while nothing changed)."""
        key = self._version()
        if key != self._key or self._weights is None:
            with torch.no_grad():
                self._weights = rearrange(self.predictor, self.schedule, self.dtype)
            self._key = key
            self.generation += 1
        return self._weights


def _ifog(w: torch.Tensor, hid: int) -> torch.Tensor:
    """Gate rows f, i, g, o (the model's order, Eq. 11-16) -> i, f, o, 2g: the g rows doubled,
    so one sigmoid covers all four gates and tanh(g) = 2 sigmoid(2g) - 1 (tanh is 5-6x slower
    than sigmoid on this machine's torch build, docs/planner.md)."""
    return torch.cat([w[hid:2 * hid], w[:hid], w[3 * hid:], 2.0 * w[2 * hid:3 * hid]])


def _merged_kernel(convs: list, sch: Schedule) -> tuple[torch.Tensor, torch.Tensor]:
    """The kernels as one of width ``sch.width`` and padding ``sch.pad`` (each at offset
    P - p_i inside zeros: the same sums), [C, 4, width], and the biases [C]."""
    c_out, ref = sch.channels, convs[0].weight
    kernel = torch.zeros((sch.conv_width, convs[0].in_channels, sch.width), dtype=ref.dtype,
                         device=ref.device)
    for i, conv in enumerate(convs):
        off = sch.pad - int(conv.padding[0])
        kernel[i * c_out:(i + 1) * c_out, :, off:off + int(conv.kernel_size[0])] = conv.weight
    return kernel, torch.cat([conv.bias for conv in convs])


def _conv_matrix(kernel: torch.Tensor, sch: Schedule,
                 positions: list[tuple[int, int]]) -> torch.Tensor:
    """The convolution at (window offset o, position j) pairs as one dense (Toeplitz) matrix
    [h*4, len(positions)*C] over the rows of the oldest window: tap t of position j of window
    k + o reads that window's row j - P + t, i.e. row o + j - P + t of window k."""
    n_in = kernel.shape[1]
    mat = torch.zeros((sch.h, n_in, len(positions), sch.conv_width), dtype=kernel.dtype,
                      device=kernel.device)
    for col, (o, j) in enumerate(positions):
        for tap in range(sch.width):
            r = j - sch.pad + tap
            if 0 <= r < sch.h:
                mat[o + r, :, col, :] = kernel[:, :, tap].t()
    return mat.reshape(sch.h * n_in, len(positions) * sch.conv_width).contiguous()


def rearrange(p: Any, sch: Schedule, dtype: torch.dtype | None = None) -> Weights:
    """:class:`Weights` of predictor ``p`` in ``dtype`` (default: the predictor's own; another
    dtype rearranges a converted copy, so no product is rounded in the narrower one)."""
    if dtype is not None and p.in_mean.dtype != dtype:
        p = copy.deepcopy(p).to(dtype)
    body = p.body
    kernel, bias = _merged_kernel(list(body.conv.convs), sch)
    hid, lstm = sch.hidden, body.lstm
    mlp = list(body.attention.mlp)
    reg = [m for m in body.regressor if isinstance(m, nn.Linear)]
    w_x, b_x, w_h = (_ifog(lstm.w_x.weight, hid), _ifog(lstm.w_x.bias, hid),
                     _ifog(lstm.w_h.weight, hid))
    # attention (Eq. 8) with sigmoid for tanh: W_2 tanh(a) + b_2 = 2 W_2 sigmoid(2a) + b_2 - W_2 1
    w_a2 = mlp[2].weight
    # the head returns F_k + out_mean + out_std dF (normalised inputs): fold scale and shift
    scale, shift = p.out_std / p.in_std[2:4], p.out_mean / p.in_std[2:4]
    head = torch.cat([reg[-1].weight.t() * scale, (reg[-1].bias * scale + shift).unsqueeze(0)])
    ones = torch.ones((1, sch.channels), dtype=kernel.dtype, device=kernel.device)
    return Weights(
        conv_wave=_conv_matrix(kernel, sch, sch.wave),
        conv_wave_bias=bias.repeat(len(sch.wave)),
        conv_all=_conv_matrix(kernel, sch, [(0, j) for j in range(sch.length)]),
        conv_all_bias=bias.repeat(sch.length),
        att1_weight_t=(2.0 * mlp[0].weight).t().contiguous(), att1_bias=2.0 * mlp[0].bias,
        att2_weight_t=(2.0 * w_a2).t().contiguous(), att2_bias=mlp[2].bias - w_a2.sum(dim=1),
        # |logit| <= sum |W_2| + |b_2| (tanh is bounded): exp() cannot overflow below ~88
        att_shift=bool((w_a2.abs().sum(dim=1) + mlp[2].bias.abs()).max() > 60.0),
        scale_expand=torch.kron(torch.eye(sch.n_scales, dtype=kernel.dtype,
                                          device=kernel.device), ones),
        wx_t=w_x.t().contiguous(), bx=b_x.contiguous(), wh_t=w_h.t().contiguous(),
        wx_gates_aug=torch.cat([w_x.t(), b_x.unsqueeze(0)]).view(-1, 4, hid).permute(1, 0, 2)
        .contiguous(),
        wh_gates=w_h.t().reshape(hid, 4, hid).permute(1, 0, 2).contiguous(),
        fc1_h_t=reg[0].weight[:, :hid].t().contiguous(),
        fc1_v=reg[0].weight[:, hid].contiguous(), fc1_bias=reg[0].bias.contiguous(),
        fc_layers=(*(torch.cat([m.weight.t(), m.bias.unsqueeze(0)]).contiguous()
                     for m in reg[1:-1]), head.contiguous()),
        in_mean=p.in_mean.clone(), in_std=p.in_std.clone(),
    )
