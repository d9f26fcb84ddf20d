"""Buffers and views of one fused rollout of N samples over S model steps (``fused.py``).

Everything the model-step loop touches is made once per (N, S, weights): at N = 50 creating a
slice costs about as much as the op that reads it, and a fresh multi-megabyte tensor per step
cost more in page faults than its matmul at N = 1000. The loop (Python in ``fused.py``, C++ in
``csrc/rollout_loop.cpp``) reads these records by field name; the C++ loop receives them as
dicts of named tensors (``native_loop.bind``).

Layouts: LSTM gates are gate-major [4, rows, hidden] in the order i, f, o, g (g doubled), so
one sigmoid covers all four and every elementwise op reads contiguous memory (on column slices of a
[rows, 4 hidden] matrix tanh was 4x slower at N = 50, docs/planner.md). Wavefront projections
are position-major (row = position * N + sample). Regressor activations carry a ones column, so
each next layer's bias is a row of its weight matrix (``addmm`` would copy a bias first).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from .fused_weights import Schedule, Weights


class Cell(NamedTuple):
    """One LSTM cell update (Eq. 11-16) over ``rows`` rows, gate-major (i, f, o, 2g)."""

    x_proj: torch.Tensor | None  # W_x x + b of these rows, added with W_h h (None: in gates)
    h_prev: torch.Tensor         # h_{t-1} [rows, hid] expanded to [4, rows, hid]
    gates: torch.Tensor          # pre-activations [4, rows, hid] (the g gate doubled)
    sig: torch.Tensor            # sigmoid of all four [4, rows, hid]
    c: torch.Tensor              # cell state [rows, hid], updated in place
    sig_i: torch.Tensor          # sig[0]
    sig_f: torch.Tensor          # sig[1]
    sig_g: torch.Tensor          # sig[3] = sigmoid(2g): tanh(g) = 2 sig_g - 1
    tanh_c: torch.Tensor         # sigmoid(2c) [rows, hid]: tanh(c) = 2 tanh_c - 1
    sig_o: torch.Tensor          # sig[2]
    h_out: torch.Tensor          # h_t [rows, hid]


class Step(NamedTuple):
    """Model step k: the wavefront's batched cell update, window k's last positions, F_{k+1}."""

    window: torch.Tensor          # window k's normalised rows [N, h*4] (view of the buffer)
    h_prev: torch.Tensor          # h of the in-flight windows, [4, c*N, hid] (expanded)
    gates: torch.Tensor           # their pre-activations [4, c*N, hid]
    gates_interior: torch.Tensor  # the windows at the interior position [4, n_int, N, hid]
    edge_proj: torch.Tensor | None   # top-edge projections of the newest windows
    gates_edge: torch.Tensor | None  # their gate rows
    cells: tuple[Cell, ...]       # the in-flight block, then window k's bottom-edge positions
    h_last_window: torch.Tensor | None  # h_L of window k when it has no bottom edge (P = 0)
    fc1_v_bias: torch.Tensor      # v_{k+1} w_v + b_1 of the first FC layer [N, width1]
    force_prev: torch.Tensor      # normalised F_k [N, 2] (view of the buffer)
    force_next: torch.Tensor      # normalised F_{k+1} [N, 2], written by the head


class Shared(NamedTuple):
    """Buffers every step reuses (conv, attention, projections, regressor)."""

    conv: torch.Tensor            # conv of the wavefront positions [N, nw*C]
    conv_rows: torch.Tensor       # the same as [N*nw, C] (sample-major rows)
    conv_by_sample: torch.Tensor  # the same as [N, nw, C]
    att_hidden: torch.Tensor      # sigmoid(2 (W_1 S + b_1)) [N*nw, a_hid] (Eq. 8, rearranged)
    att_logits: torch.Tensor      # [N*nw, n_scales], turned into the softmax in place (Eq. 9)
    att_sum: torch.Tensor         # [N*nw, 1]
    scale_weights: torch.Tensor   # each scale's weight over its channels [N*nw, C]
    scale_weights_by_sample: torch.Tensor  # the same as [N, nw, C]
    weighted_s: torch.Tensor      # weighted S (Eq. 10), written position-major [N, nw, C] view
    lstm_input_x4: torch.Tensor   # [weighted S, 1] position-major, expanded [4, nw*N, C + 1]
    x_proj: torch.Tensor          # W_x x + b [4, nw*N, hid], gate-major, position-major rows
    x_proj_interior: torch.Tensor  # the interior position's [4, 1, N, hid] (broadcast)
    h_last: torch.Tensor          # h_L of window k [N, hid]
    fc_in: tuple[torch.Tensor, ...]   # regressor activations [N, width + 1] (ones column)
    fc_out: tuple[torch.Tensor, ...]  # the columns each FC layer writes (fc_in[i][:, :-1])


class PrologueCell(NamedTuple):
    """Windows 0..i at absolute position i (batch 1 each), gates as columns i, f, o, 2g."""

    x_proj: torch.Tensor   # their W_x x + b [i + 1, 4 hid] (strided view)
    h: torch.Tensor        # [i + 1, hid], updated in place
    c: torch.Tensor
    gates: torch.Tensor    # [i + 1, 4 hid]
    sig: torch.Tensor      # sigmoid of all four [i + 1, 4 hid]
    sig_i: torch.Tensor    # its column blocks
    sig_f: torch.Tensor
    sig_g: torch.Tensor
    sig_o: torch.Tensor
    tanh_c: torch.Tensor


@dataclass
class Workspace:
    """All buffers and views of one (N, S) rollout; see the module docstring."""

    n: int
    s: int
    buffer: torch.Tensor          # normalised rows [N, h + S, 4]: the window, then predicted
    steps: tuple[Step, ...]
    shared: Shared
    prologue_rows: torch.Tensor   # measured rows, then zeros [D - 1 + h, 4]
    prologue_windows: torch.Tensor  # windows 0..D-1 of those rows [D, h*4] (strided view)
    prologue: dict[str, torch.Tensor]  # conv/attention/projection buffers of the prologue
    prologue_cells: tuple[PrologueCell, ...]
    prologue_h: torch.Tensor      # [D, hid]
    prologue_c: torch.Tensor
    h: torch.Tensor               # LSTM state per window [max(S, D), N, hid]
    c: torch.Tensor
    fc1_v_bias: torch.Tensor      # [S, N, width1]
    v_norm_t: torch.Tensor        # normalised v_{k+1} per step [S, N, 1] (view of the buffer)
    native: object | None = None  # the C++ loop bound to these tensors (native_loop.bind)


def build_workspace(sch: Schedule, w: Weights, n: int, s: int) -> Workspace:
    """Allocate the buffers of an (N, S) rollout and make every view the loop reads."""
    dtype, dev = w.in_mean.dtype, w.in_mean.device

    def e(*shape: int) -> torch.Tensor:
        return torch.empty(shape, dtype=dtype, device=dev)

    buffer = e(n, sch.h + s, 4)
    shared = _shared(sch, w, n, s, e)
    h_state, c_state = e(max(s, sch.depth), n, sch.hidden), e(max(s, sch.depth), n, sch.hidden)
    fc1_v_bias = e(s, n, w.fc1_h_t.shape[1])
    steps = _steps(sch, buffer, shared, h_state, c_state, fc1_v_bias, e)
    return Workspace(n=n, s=s, buffer=buffer, steps=steps, shared=shared,
                     **_prologue(sch, w, e), h=h_state, c=c_state, fc1_v_bias=fc1_v_bias,
                     v_norm_t=buffer[:, sch.h:, 1].t().unsqueeze(-1))


def _shared(sch: Schedule, w: Weights, n: int, s: int, e) -> Shared:
    nw, c_all, hid = len(sch.wave), sch.conv_width, sch.hidden
    rows = nw * n
    conv = e(n, nw * c_all)
    lstm_input = e(nw, n, c_all + 1)  # position-major; the ones column carries b of W_x x + b
    lstm_input[..., c_all] = 1.0
    x_proj = e(4, rows, hid)
    scale_weights = e(rows, c_all)
    fc_in = [e(n, w.fc1_h_t.shape[1] + 1)] + [e(n, wl.shape[1] + 1) for wl in w.fc_layers[:-1]]
    for y in fc_in:
        y[:, -1] = 1.0
    return Shared(
        conv=conv, conv_rows=conv.view(rows, c_all), conv_by_sample=conv.view(n, nw, c_all),
        att_hidden=e(rows, w.att1_weight_t.shape[1]), att_logits=e(rows, sch.n_scales),
        att_sum=e(rows, 1), scale_weights=scale_weights,
        scale_weights_by_sample=scale_weights.view(n, nw, c_all),
        weighted_s=lstm_input[..., :c_all].transpose(0, 1),
        lstm_input_x4=lstm_input.view(rows, c_all + 1).unsqueeze(0).expand(4, rows, c_all + 1),
        x_proj=x_proj, x_proj_interior=x_proj[:, sch.pad * n:(sch.pad + 1) * n].unsqueeze(1),
        h_last=e(n, hid), fc_in=tuple(fc_in), fc_out=tuple(y[:, :-1] for y in fc_in))


def _steps(sch: Schedule, buffer: torch.Tensor, sh: Shared, h_state: torch.Tensor,
           c_state: torch.Tensor, fc1_v_bias: torch.Tensor, e) -> tuple[Step, ...]:
    """The views of every model step (the wavefront schedule of ``fused.py``)."""
    hid, pad, depth = sch.hidden, sch.pad, sch.depth
    n, s = buffer.shape[0], buffer.shape[1] - sch.h
    row = (sch.h + s) * 4
    flat = buffer.view(n, row)
    gate_bufs: dict[int, tuple[torch.Tensor, ...]] = {}  # one set per row count

    def cell(count: int, k0: int, x_proj: torch.Tensor | None,
             h_out: torch.Tensor | None = None) -> Cell:
        """Windows k0..k0+count-1 (rows of the per-window LSTM state)."""
        m = count * n
        if m not in gate_bufs:
            gate_bufs[m] = (e(4, m, hid), e(4, m, hid), e(m, hid))
        gates, sig, tanh_c = gate_bufs[m]
        h_view = h_state[k0:k0 + count].view(m, hid)
        return Cell(x_proj=x_proj, h_prev=h_view.unsqueeze(0).expand(4, m, hid), gates=gates,
                    sig=sig, c=c_state[k0:k0 + count].view(m, hid), sig_i=sig[0],
                    sig_f=sig[1], sig_g=sig[3], tanh_c=tanh_c, sig_o=sig[2],
                    h_out=h_view if h_out is None else h_out)

    bottom = [sh.x_proj[:, (pad + p) * n:(pad + p + 1) * n] for p in range(1, pad + 1)]
    steps = []
    for k in range(s):
        count = min(depth, s - k)  # windows k..k+count-1 in flight (later ones are not needed)
        n_int = min(count, depth - pad)
        n_edge = count - n_int
        block = cell(count, k, None)
        cells = [block] + [cell(1, k, bottom[p], sh.h_last if p == pad - 1 else None)
                           for p in range(pad)]
        steps.append(Step(
            window=flat.as_strided((n, sch.h * 4), (row, 1), k * 4), h_prev=block.h_prev,
            gates=block.gates,
            gates_interior=block.gates[:, :n_int * n].view(4, n_int, n, hid),
            edge_proj=sh.x_proj[:, :n_edge * n] if n_edge else None,
            gates_edge=block.gates[:, n_int * n:count * n] if n_edge else None,
            cells=tuple(cells), h_last_window=h_state[k] if pad == 0 else None,
            fc1_v_bias=fc1_v_bias[k], force_prev=buffer[:, sch.h + k - 1, 2:4],
            force_next=buffer[:, sch.h + k, 2:4]))
    return tuple(steps)


def _prologue(sch: Schedule, w: Weights, e) -> dict:
    """Buffers of the measured-only prologue: windows 0..D-1 with batch 1 (``fused.py``)."""
    depth, length, hid, h = sch.depth, sch.length, sch.hidden, sch.h
    rows = torch.zeros((depth - 1 + h, 4), dtype=w.in_mean.dtype, device=w.in_mean.device)
    conv, x_proj = e(depth, length * sch.conv_width), e(depth * length, 4 * hid)
    buffers = {"conv": conv, "conv_rows": conv.view(depth * length, sch.conv_width),
               "conv_by_scale": conv.view(depth * length, sch.n_scales, sch.channels),
               "att_hidden": e(depth * length, w.att1_weight_t.shape[1]), "x_proj": x_proj}
    h_p, c_p, gates = e(depth, hid), e(depth, hid), e(depth, 4 * hid)
    sig, tanh_c = e(depth, 4 * hid), e(depth, hid)
    cells = []
    for i in range(sch.last_interior):  # windows 0..i at positions i - d: absolute position i
        a = i + 1
        cells.append(PrologueCell(
            x_proj=x_proj.as_strided((a, 4 * hid), ((length - 1) * 4 * hid, 1), i * 4 * hid),
            h=h_p[:a], c=c_p[:a], gates=gates[:a], sig=sig[:a], sig_i=sig[:a, :hid],
            sig_f=sig[:a, hid:2 * hid], sig_g=sig[:a, 3 * hid:], sig_o=sig[:a, 2 * hid:3 * hid],
            tanh_c=tanh_c[:a]))
    return {"prologue_rows": rows,
            "prologue_windows": rows.view(-1).as_strided((depth, h * 4), (4, 1)),
            "prologue": buffers, "prologue_cells": tuple(cells), "prologue_h": h_p,
            "prologue_c": c_p}
