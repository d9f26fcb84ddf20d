"""A faster rollout of the ``ours`` / ``cnn-lstm`` forward model, equal to float rounding.

The planner calls the forward model S = H x steps_per_horizon_step times in sequence per plan
(25 for N=50, H=5; 50 for H=10). Each call runs the convolutions (Eq. 7), the scale attention
(Eq. 8-10), the LSTM (Eq. 11-16) over the L = h - 1 positions of the h-sample window and the
regressor. :class:`FusedRollout` computes the same function as the reference dynamics (the
model stepped with ``ForcePredictor.predict``; ``test_planner_dynamics`` compares them) with
fewer operations, fewer FLOPs and no per-step allocation:

* **Weights prepared once** (``fused_weights.py``), rebuilt only when the predictor changes.
* **One convolution as one matmul.** The three kernels (widths k_i, paddings p_i) become one
  kernel of width ``max(k_i + P - p_i)``, padding ``P = max(p_i)``, each kernel at offset
  ``P - p_i`` inside a zero kernel (exactly the same sums); over an h-row window that
  convolution is one dense (Toeplitz) matrix [h*4, positions*channels].
* **Wavefront over consecutive windows.** The window slides one row per model step. A position
  j whose receptive field lies inside the window (``P <= j <= J = h + P - W``, "interior") sees
  the same rows as position j - 1 of the next window, and window k + 1's LSTM does not need
  window k's prediction until its position J. So at step k the D = J + 1 windows k..k+J each
  advance one position (window k + d at position J - d), as **one batched LSTM step** of
  D x N rows: for d <= J - P that position is the interior position of absolute index k + J,
  one projection ``W_x x + b`` shared by all of them (added by broadcasting); for the P
  newest windows it is a top-edge (zero-padded) position, computed for that window. Window k
  then runs its P bottom-edge positions alone and goes to the regressor. Per step 2P + 1
  positions are projected (5 of 9 for ``ours``, 3 of 9 for ``cnn-lstm``) and the LSTM takes
  P + 1 sequential cell updates instead of L = 9 (3 instead of 9 for ``ours``).
* **Measured-only prologue, once for all samples.** Before step 0, windows 0..J have already
  processed their positions that see measured rows only; those are identical for all N
  samples, so they run with batch 1 (windows batched, one anti-diagonal per position) and the
  LSTM states are broadcast to the N samples.
* **LSTM by hand, gate-major** (i, f, o, g; ``fused_workspace.py``). torch's fused
  ``torch.lstm`` / ``nn.LSTM`` was measured slower here (docs/planner.md): it recomputes the
  input projection of all positions and allocates per call.
* **sigmoid for tanh.** In this torch build tanh runs 5-6x slower than sigmoid on this CPU
  (docs/planner.md). tanh(x) = 2 sigmoid(2x) - 1: the g gate's weights are doubled, so one
  sigmoid covers all four gates; tanh(c) is 2 sigmoid(c + c) - 1; the attention's tanh layer
  has its weights doubled and the next layer absorbs the 2 s - 1 (``fused_weights.rearrange``).
  Float rounding only.
* **Biases inside the matmuls**: the input projection reads [weighted S, 1] (a ones column
  carries b), every FC layer after the first reads [y, 1]; the first FC layer's v_{k+1} term and
  bias are computed for all S steps in one op before the loop; the last layer carries the
  increment head's scale and shift (in units of the normalised force), so ``F_{k+1} = F_k + y``
  is one ``addmm`` into the rollout buffer. ReLU is ``relu_``. The scale-attention softmax skips
  its max-shift when the logits are provably small (``|a| <= sum |W_2| + |b_2| <= 60``).
* **Workspace reused** (``fused_workspace.py``) between calls of the same (N, S).
* **The model-step loop in C++** when it is built (``native_loop.py``,
  ``csrc/rollout_loop.cpp``): the same ATen calls in the same order on the same workspace
  tensors, handed over by name, so the results are bit-identical to :func:`run_steps` below,
  the Python loop (``test_planner_dynamics`` compares them bit for bit).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch

from .fused_weights import FusedWeights, Schedule, Weights
from .fused_workspace import Workspace, build_workspace


def lstm_pointwise(gates: torch.Tensor, sig: torch.Tensor, c: torch.Tensor,
                   sig_i: torch.Tensor, sig_f: torch.Tensor, sig_g: torch.Tensor,
                   tanh_c: torch.Tensor, sig_o: torch.Tensor, h_out: torch.Tensor) -> None:
    """Eq. 11-16 after the gate pre-activations (i, f, o, 2g): one sigmoid for all four,
    c = f c + i tanh(g) with tanh(g) = 2 sigmoid(2g) - 1, h = o tanh(c) = 2 o sigmoid(2c) - o
    (tanh is 5-6x slower than sigmoid in this torch build), all into preallocated views,
    without Python scalars (each became a tensor conversion). ``tanh_c`` holds sigmoid(2c)."""
    torch.sigmoid(gates, out=sig)
    c.mul_(sig_f).addcmul_(sig_i, sig_g, value=2.0).sub_(sig_i)
    torch.add(c, c, out=tanh_c)
    tanh_c.sigmoid_()
    torch.mul(sig_o, tanh_c, out=h_out)
    h_out.add_(h_out).sub_(sig_o)


def run_prologue(ws: Workspace, w: Weights, sch: Schedule, base_norm: torch.Tensor) -> None:
    """Windows 0..J over their positions that see measured rows only, batch 1 (the same for
    every sample), then their LSTM states broadcast to the N samples."""
    ws.prologue_rows[:sch.h] = base_norm
    p = ws.prologue
    conv = p["conv"]
    torch.addmm(w.conv_all_bias, ws.prologue_windows, w.conv_all, out=conv)  # Eq. 7
    conv.relu_()
    torch.addmm(w.att1_bias, p["conv_rows"], w.att1_weight_t, out=p["att_hidden"])  # Eq. 8
    p["att_hidden"].sigmoid_()  # tanh, with the weights rearranged
    logits = torch.addmm(w.att2_bias, p["att_hidden"], w.att2_weight_t)
    # softmax over the scales (Eq. 9); torch.softmax is slow for a last dim of 3
    e = torch.exp(logits - logits.amax(dim=-1, keepdim=True)) if w.att_shift else logits.exp_()
    p["conv_by_scale"].mul_((e / e.sum(dim=-1, keepdim=True)).unsqueeze(-1))  # Eq. 10
    torch.addmm(w.bx, p["conv_rows"], w.wx_t, out=p["x_proj"])
    ws.prologue_h.zero_()
    ws.prologue_c.zero_()
    for x_proj, h, c, gates, sig, sig_i, sig_f, sig_g, sig_o, tanh_c in ws.prologue_cells:
        torch.addmm(x_proj, h, w.wh_t, out=gates)
        lstm_pointwise(gates, sig, c, sig_i, sig_f, sig_g, tanh_c, sig_o, h)
    depth, n, hid = sch.depth, ws.n, sch.hidden
    ws.h[:depth].copy_(ws.prologue_h.unsqueeze(1).expand(depth, n, hid))
    ws.c[:depth].copy_(ws.prologue_c.unsqueeze(1).expand(depth, n, hid))
    ws.h[depth:].zero_()  # windows D.. start from h_0 = c_0 = 0
    ws.c[depth:].zero_()


def run_steps(ws: Workspace, w: Weights) -> None:
    """The model-step loop in Python (the C++ loop makes the same calls): per step, the conv
    (Eq. 7) and scale attention (Eq. 8-10) of the wavefront positions, their ``W_x x + b``,
    the batched LSTM update of the in-flight windows and window k's bottom edges (Eq. 11-16),
    and the regressor (3.1.3) writing F_{k+1} = F_k + y into the buffer."""
    sh = ws.shared
    mm, bmm, addmm, baddbmm, mul = torch.mm, torch.bmm, torch.addmm, torch.baddbmm, torch.mul
    hidden_layers = list(zip(sh.fc_in[:-1], w.fc_layers[:-1], sh.fc_out[1:], strict=True))
    head_in, head_weight = sh.fc_in[-1], w.fc_layers[-1]
    for (window, h_prev, gates, gates_interior, edge_proj, gates_edge, cells, h_last_window,
         fc1_v_bias, force_prev, force_next) in ws.steps:
        addmm(w.conv_wave_bias, window, w.conv_wave, out=sh.conv)
        sh.conv.relu_()
        addmm(w.att1_bias, sh.conv_rows, w.att1_weight_t, out=sh.att_hidden)
        sh.att_hidden.sigmoid_()  # tanh, with the weights rearranged
        addmm(w.att2_bias, sh.att_hidden, w.att2_weight_t, out=sh.att_logits)
        if w.att_shift:
            sh.att_logits.sub_(sh.att_logits.amax(dim=-1, keepdim=True))
        sh.att_logits.exp_()
        torch.sum(sh.att_logits, dim=-1, keepdim=True, out=sh.att_sum)
        sh.att_logits.div_(sh.att_sum)
        mm(sh.att_logits, w.scale_expand, out=sh.scale_weights)
        mul(sh.conv_by_sample, sh.scale_weights_by_sample, out=sh.weighted_s)
        bmm(sh.lstm_input_x4, w.wx_gates_aug, out=sh.x_proj)
        # W_h h of all in-flight windows, + the shared interior and the top-edge projections
        bmm(h_prev, w.wh_gates, out=gates)
        gates_interior.add_(sh.x_proj_interior)
        if edge_proj is not None:
            gates_edge.add_(edge_proj)
        for (x_proj, c_h_prev, c_gates, sig, c, sig_i, sig_f, sig_g, tanh_c, sig_o,
             h_out) in cells:
            if x_proj is not None:
                baddbmm(x_proj, c_h_prev, w.wh_gates, out=c_gates)
            lstm_pointwise(c_gates, sig, c, sig_i, sig_f, sig_g, tanh_c, sig_o, h_out)
        if h_last_window is not None:
            sh.h_last.copy_(h_last_window)
        addmm(fc1_v_bias, sh.h_last, w.fc1_h_t, out=sh.fc_out[0])
        for y, weight, y_out in hidden_layers:
            y.relu_()  # the ones column stays 1
            mm(y, weight, out=y_out)
        head_in.relu_()
        addmm(force_prev, head_in, head_weight, out=force_next)


class FusedRollout:
    """Rolls N samples out from one window: a workspace per (N, S), the prologue and the
    model-step loop (C++ when built and ``native``, else :func:`run_steps`).

    Not thread-safe: each rollout worker has its own (``fused_dynamics.py``).
    """

    def __init__(self, weights: FusedWeights, *, native: bool = True,
                 max_workspaces: int = 4) -> None:
        self.weights = weights
        self.schedule = weights.schedule
        self.native = bool(native)
        self.max_workspaces = max_workspaces
        self._workspaces: OrderedDict[tuple, Workspace] = OrderedDict()

    def workspace(self, w: Weights, n: int, s: int) -> Workspace:
        """The workspace of (N, S) for the current weights (kept for the last few sizes: the
        chunks of a batch have at most two)."""
        key = (self.weights.generation, n, s)
        ws = self._workspaces.get(key)
        if ws is None:
            ws = build_workspace(self.schedule, w, n, s)
            if self.native:
                from .native_loop import bind

                ws.native = bind(ws, w)
            self._workspaces[key] = ws
            while len(self._workspaces) > self.max_workspaces:
                self._workspaces.popitem(last=False)
        return ws

    def rollout(self, w: Weights, window: np.ndarray, v: torch.Tensor,
                dt_s: float) -> torch.Tensor:
        """(q, fx, fz) [N, S, 3] from the last h rows ``window`` [h, 4] for ``v`` [N, S],
        with the weights ``w`` (= ``self.weights.current()``, read once by the caller)."""
        sch = self.schedule
        n, s = v.shape
        ws = self.workspace(w, n, s)
        mean, std = w.in_mean, w.in_std
        v = v.to(dtype=mean.dtype, device=mean.device)
        base = torch.as_tensor(window, dtype=mean.dtype, device=mean.device)
        base_norm = (base - mean) / std
        buf = ws.buffer
        buf[:, :sch.h] = base_norm
        q = base[-1, 0] + dt_s * torch.cumsum(v, dim=1)  # q_{s+1} = q_s + v_s dt
        buf[:, sch.h:, 0] = (q - mean[0]) / std[0]
        buf[:, sch.h:, 1] = (v - mean[1]) / std[1]
        run_prologue(ws, w, sch, base_norm)
        # the first FC layer's v_{k+1} term + bias of every step: v_{k+1} w_v + b_1
        torch.addcmul(w.fc1_bias, ws.v_norm_t, w.fc1_v, out=ws.fc1_v_bias)
        if ws.native is not None:
            ws.native.run()
        else:
            run_steps(ws, w)
        forces = buf[:, sch.h:, 2:4] * std[2:4] + mean[2:4]
        return torch.cat([q.unsqueeze(-1), forces], dim=-1)
