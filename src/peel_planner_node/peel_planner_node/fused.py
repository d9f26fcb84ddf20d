"""A faster, numerically equivalent rollout of the ``ours`` / ``cnn-lstm`` forward model.

The planner calls the forward model S = H x steps_per_horizon_step times in sequence per plan
(25 for N=50, H=5; 50 for H=10). Each call runs the convolutions (Eq. 7), the scale attention
(Eq. 8-10), the LSTM (Eq. 11-16) over the L = h - 1 positions of the h-sample window and the
regressor. This module computes the same function as ``ForcePredictor.predict`` in that loop
(to float rounding; ``test_planner_dynamics`` checks it against the step-by-step loop) with
fewer operations, fewer FLOPs and no per-step allocation of the large intermediates:

* **Weights prepared once.** The rearranged weights (below) are built on the first rollout and
  rebuilt only when the predictor's weights change: the cache key is every parameter's and
  buffer's ``(data_ptr, _version)``; ``_version`` is bumped by every in-place update
  (``add_``, ``copy_``, ``load_state_dict``, an optimiser step), so MAML's in-place updates
  (Algorithm 1) are picked up; a new ``LearnedDynamics`` (``Planner.set_dynamics``) starts empty.
* **One convolution as one matmul.** The three kernels (widths k_i, paddings p_i) become one
  kernel of width ``max(k_i + P - p_i)``, padding ``P = max(p_i)``, each kernel at offset
  ``P - p_i`` inside a zero kernel (exactly the same sums); over an h-row window that
  convolution is one dense (Toeplitz) matrix [h*4, positions*channels].
* **Shift-invariant positions are computed once.** The window slides one row per model step.
  A position j whose receptive field lies inside the window (``P <= j`` and
  ``j - P + width <= h``, "interior") gives the same conv output, attention weights and LSTM
  input projection ``W_x x_j + b`` at the next step as position j + 1 did at this one; only the
  zero-padded edge positions and the newest interior position are computed anew (5 of 9 for
  ``ours``, 3 of 9 for ``cnn-lstm``). The projections are stored per absolute row in one
  time-major buffer, which the recurrence reads as contiguous [N, 4 hidden] slices.
* **LSTM by hand, gate rows reordered** (this model's f, i, g, o -> i, f, o, g: one sigmoid over
  the first three blocks), every intermediate written into preallocated buffers (``out=``).
  torch's fused ``torch.lstm`` / ``nn.LSTM`` was measured slower here (docs/planner.md): it
  recomputes the input projection of all positions and allocates per call.
* **Regressor input as one buffer** [h_L, v_{k+1}, 1] so the first FC layer (with its bias) is
  one matmul; the rollout buffer is kept in normalised units, so the force update of the
  increment head ``F_{k+1} = F_k + out_mean + out_std * dF`` is one ``addcmul``.
* **Workspace reused** between calls of the same (N, S): the first call allocates, later calls
  write into the same memory (a fresh multi-megabyte tensor per step cost more in page faults
  and bias copies than its matmul at N = 1000).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn


class FusedConvAttentionLSTM:
    """Fused rollout of a ``ForcePredictor`` whose body is ``ConvAttentionLSTM``."""

    @staticmethod
    def supports(predictor: Any) -> bool:
        """True when ``predictor`` has the exact module structure this class reproduces."""
        try:
            from model_learner_node.model import LSTM, ConvAttentionLSTM
        except ImportError:  # pragma: no cover - the package is a declared dependency
            return False
        body = getattr(predictor, "body", None)
        if not isinstance(body, ConvAttentionLSTM) or not isinstance(body.lstm, LSTM):
            return False
        mlp = list(body.attention.mlp)
        if len(mlp) != 3 or not (isinstance(mlp[0], nn.Linear) and isinstance(mlp[1], nn.Tanh)
                                 and isinstance(mlp[2], nn.Linear)):
            return False
        reg = list(body.regressor)
        if not reg or not isinstance(reg[-1], nn.Linear) or len(reg) % 2 != 1:
            return False
        for i, layer in enumerate(reg[:-1]):
            want = nn.Linear if i % 2 == 0 else nn.ReLU
            if not isinstance(layer, want):
                return False
        convs = list(body.conv.convs)
        return not any(c.stride != (1,) or c.dilation != (1,) or c.groups != 1 for c in convs)

    def __init__(self, predictor: Any) -> None:
        self.predictor = predictor
        body = predictor.body
        self.h = int(predictor.h)
        convs = list(body.conv.convs)
        self.channels = convs[0].out_channels
        self.n_scales = len(convs)
        self.pad = max(int(c.padding[0]) for c in convs)
        self.width = max(int(c.kernel_size[0]) + self.pad - int(c.padding[0]) for c in convs)
        self.length = self.h + 2 * self.pad - self.width + 1  # L positions per window
        self.hidden = int(body.lstm.hidden)
        interior = [j for j in range(self.length)
                    if j >= self.pad and j - self.pad + self.width <= self.h]
        # positions whose projection is carried over from the previous step (j + 1 interior too)
        self.reused = [j for j in interior if j + 1 in interior]
        self.fresh = [j for j in range(self.length) if j not in self.reused]
        self._key: tuple | None = None
        self._w: dict[str, Any] = {}
        self._ws_key: tuple | None = None
        self._ws: dict[str, torch.Tensor] = {}

    # ------------------------------------------------------------------ weights
    def _version(self) -> tuple:
        p = self.predictor
        return tuple((t.data_ptr(), t._version, t.dtype, t.device)
                     for t in (*p.parameters(), *p.buffers()))

    def _weights(self) -> dict[str, Any]:
        """The predictor's current weights, rearranged for the fused ops (cached, see above)."""
        key = self._version()
        if key == self._key:
            return self._w
        with torch.no_grad():
            self._w = self._build_weights()
        self._key = key
        self._ws_key = None  # dtype/device may have changed
        return self._w

    def _build_weights(self) -> dict[str, Any]:
        p = self.predictor
        body = p.body
        convs = list(body.conv.convs)
        c_out, n_in = self.channels, convs[0].in_channels
        ref = convs[0].weight
        c_all = c_out * len(convs)
        wc = torch.zeros((c_all, n_in, self.width), dtype=ref.dtype, device=ref.device)
        for i, conv in enumerate(convs):
            off = self.pad - int(conv.padding[0])
            k = int(conv.kernel_size[0])
            wc[i * c_out:(i + 1) * c_out, :, off:off + k] = conv.weight.detach()
        bc = torch.cat([conv.bias.detach() for conv in convs])
        # the convolution over a window, per position: toe[row, in, j, out]
        h, pad, width, length = self.h, self.pad, self.width, self.length
        toe = torch.zeros((h, n_in, length, c_all), dtype=ref.dtype, device=ref.device)
        for j in range(length):
            for tap in range(width):
                row = j - pad + tap
                if 0 <= row < h:
                    toe[row, :, j, :] = wc[:, :, tap].t()
        toe = toe.reshape(h * n_in, length, c_all)
        hid = self.hidden

        def ifog(w: torch.Tensor) -> torch.Tensor:  # gate rows f, i, g, o -> i, f, o, g
            return torch.cat([w[hid:2 * hid], w[:hid], w[3 * hid:], w[2 * hid:3 * hid]])

        lstm = body.lstm
        mlp = list(body.attention.mlp)
        reg = [m for m in body.regressor if isinstance(m, nn.Linear)]
        w1 = reg[0].weight.detach()
        # first FC layer over [h_L, v_{k+1}, 1]
        w1_aug = torch.cat([w1.t(), reg[0].bias.detach().unsqueeze(0)], dim=0).contiguous()

        def cols(js: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
            return (toe[:, js, :].reshape(h * n_in, len(js) * c_all).contiguous(),
                    bc.repeat(len(js)))

        fresh, everything = cols(self.fresh), cols(list(range(length)))
        return {
            "toe_fresh": fresh[0], "btoe_fresh": fresh[1],
            "toe_all": everything[0], "btoe_all": everything[1],
            "wx_t": ifog(lstm.w_x.weight.detach()).t().contiguous(),
            "bx": ifog(lstm.w_x.bias.detach()).contiguous(),
            "wh_t": ifog(lstm.w_h.weight.detach()).t().contiguous(),
            "a1w_t": mlp[0].weight.detach().t().contiguous(), "a1b": mlp[0].bias.detach(),
            "a2w_t": mlp[2].weight.detach().t().contiguous(), "a2b": mlp[2].bias.detach(),
            "w1_aug": w1_aug,
            "mid": [(m.weight.detach().t().contiguous(), m.bias.detach()) for m in reg[1:]],
            "in_mean": p.in_mean.detach().clone(), "in_std": p.in_std.detach().clone(),
            "shift": (p.out_mean / p.in_std[2:4]).detach().clone(),
            "scale": (p.out_std / p.in_std[2:4]).detach().clone(),
        }

    # ------------------------------------------------------------------ workspace
    def _workspace(self, n: int, s: int, dtype: torch.dtype, dev: torch.device) -> dict:
        """Buffers and every view the loop uses, made once per (N, S): at N = 50 creating a
        slice costs about as much as the op that reads it."""
        key = (n, s, dtype, dev)
        if key == self._ws_key:
            return self._ws
        h, length, hid = self.h, self.length, self.hidden
        c_all = self.channels * self.n_scales
        w = self._w

        def e(*shape: int) -> torch.Tensor:
            return torch.empty(shape, dtype=dtype, device=dev)

        bufn = e(n, h + s, 4)
        zx = e(s + length, n, 4 * hid)  # W_x x + b per absolute position, time-major
        row = (h + s) * 4
        flat = bufn.view(n, row)

        def stage(npos: int) -> dict[str, torch.Tensor]:
            conv, zt = e(n, npos * c_all), e(npos, n, c_all)
            return {"conv": conv, "conv_t": conv.view(n, npos, c_all).transpose(0, 1),
                    "zt": zt, "zz": zt.view(npos * n, c_all),
                    "zs": zt.view(npos * n, self.n_scales, self.channels),
                    "att": e(npos * n, w["a1w_t"].shape[1])}

        fresh = self.fresh
        groups: list[tuple[int, int]] = []  # runs of consecutive fresh positions
        for i, j in enumerate(fresh):
            if groups and fresh[groups[-1][0]] + groups[-1][1] == j:
                groups[-1] = (groups[-1][0], groups[-1][1] + 1)
            else:
                groups.append((i, 1))
        st_all, st_fresh = stage(length), stage(len(fresh))

        def outs(st: dict, k: int, runs: list[tuple[int, int, int]]) -> list:
            return [(st["zt"][i:i + c].view(c * n, c_all),
                     zx[k + j:k + j + c].view(c * n, 4 * hid)) for i, c, j in runs]

        steps = []
        for k in range(s):
            if k == 0:
                st, runs = st_all, [(0, length, 0)]
                toe, btoe = w["toe_all"], w["btoe_all"]
            else:
                st, runs = st_fresh, [(i, c, fresh[i]) for i, c in groups]
                toe, btoe = w["toe_fresh"], w["btoe_fresh"]
            steps.append({"x": flat.as_strided((n, h * 4), (row, 1), k * 4), "st": st,
                          "toe": toe, "btoe": btoe, "outs": outs(st, k, runs),
                          "z": [zx[k + t] for t in range(length)],
                          "f_prev": bufn[:, h + k - 1, 2:4], "f_next": bufn[:, h + k, 2:4]})
        g, sg, hreg = e(n, 4 * hid), e(n, 3 * hid), e(n, hid + 2)
        hreg[:, hid + 1] = 1.0
        ws = {
            "bufn": bufn, "steps": steps, "g": g, "g_ifo": g[:, :3 * hid], "g_g": g[:, 3 * hid:],
            "sg": sg, "s_i": sg[:, :hid], "s_f": sg[:, hid:2 * hid], "s_o": sg[:, 2 * hid:],
            "tg": e(n, hid), "cell": e(n, hid), "tmp": e(n, hid),
            "hreg": hreg, "h_t": hreg[:, :hid], "h_v": hreg[:, hid],
            "y": [e(n, w["w1_aug"].shape[1])] + [e(n, wl.shape[1]) for wl, _ in w["mid"]],
        }
        self._ws, self._ws_key = ws, key
        return ws

    # ------------------------------------------------------------------ rollout
    def _project(self, step: dict) -> None:
        """Conv (Eq. 7) + attention (Eq. 8-10) + ``W_x x + b`` of this step's new positions."""
        w, st = self._w, step["st"]
        conv, zz = st["conv"], st["zz"]
        torch.addmm(step["btoe"], step["x"], step["toe"], out=conv)
        conv.clamp_(min=0.0)  # ReLU
        st["zt"].copy_(st["conv_t"])  # position-major
        att = st["att"]
        torch.addmm(w["a1b"], zz, w["a1w_t"], out=att)
        att.tanh_()
        a = torch.addmm(w["a2b"], att, w["a2w_t"])  # [P*N, n_scales]
        # softmax over the scales (Eq. 9); torch.softmax is slow for a last dim of 3
        e = torch.exp(a - a.amax(dim=-1, keepdim=True))
        st["zs"].mul_((e / e.sum(dim=-1, keepdim=True)).unsqueeze(-1))
        for src, out in step["outs"]:
            torch.addmm(w["bx"], src, w["wx_t"], out=out)

    def rollout(self, window: np.ndarray, v: torch.Tensor, dt_s: float) -> torch.Tensor:
        """(q, fx, fz) [N, S, 3] from the last h rows ``window`` [h, 4] for ``v`` [N, S]."""
        w = self._weights()
        h = self.h
        n, s = v.shape
        dtype, dev = w["in_mean"].dtype, w["in_mean"].device
        ws = self._workspace(n, s, dtype, dev)
        in_mean, in_std = w["in_mean"], w["in_std"]
        v = v.to(dtype=dtype, device=dev)
        base = torch.as_tensor(window, dtype=dtype, device=dev)
        bufn = ws["bufn"]
        bufn[:, :h] = (base - in_mean) / in_std
        q = base[-1, 0] + dt_s * torch.cumsum(v, dim=1)
        bufn[:, h:, 0] = (q - in_mean[0]) / in_std[0]
        vn = (v - in_mean[1]) / in_std[1]
        bufn[:, h:, 1] = vn
        sig, tanh, mul, addmm = torch.sigmoid, torch.tanh, torch.mul, torch.addmm
        g, g_ifo, g_g = ws["g"], ws["g_ifo"], ws["g_g"]
        sg, s_i, s_f, s_o = ws["sg"], ws["s_i"], ws["s_f"], ws["s_o"]
        tg, cell, tmp, h_t, h_v, hreg = (ws["tg"], ws["cell"], ws["tmp"], ws["h_t"], ws["h_v"],
                                         ws["hreg"])
        ys, mid, wh_t, w1_aug = ws["y"], w["mid"], w["wh_t"], w["w1_aug"]
        hid3 = 3 * self.hidden
        shift, scale = w["shift"], w["scale"]
        for k, step in enumerate(ws["steps"]):
            self._project(step)
            # LSTM (Eq. 11-16) over the window's positions, gates i, f, o | g; h_0 = c_0 = 0
            z = step["z"]
            sig(z[0][:, :hid3], out=sg)
            tanh(z[0][:, hid3:], out=tg)
            mul(s_i, tg, out=cell)
            tanh(cell, out=tmp)
            mul(s_o, tmp, out=h_t)
            for zt in z[1:]:
                addmm(zt, h_t, wh_t, out=g)
                sig(g_ifo, out=sg)
                tanh(g_g, out=tg)
                cell.mul_(s_f).addcmul_(s_i, tg)
                tanh(cell, out=tmp)
                mul(s_o, tmp, out=h_t)
            # regressor (3.1.3) on [h_L, v_{k+1}, 1]
            h_v.copy_(vn[:, k])
            y = torch.mm(hreg, w1_aug, out=ys[0])
            for (wl, bl), yo in zip(mid, ys[1:], strict=True):
                y.clamp_(min=0.0)
                y = addmm(bl, y, wl, out=yo)
            step["f_next"].copy_(torch.addcmul(step["f_prev"] + shift, y, scale))
        forces = bufn[:, h:, 2:4] * in_std[2:4] + in_mean[2:4]
        return torch.cat([q.unsqueeze(-1), forces], dim=-1)
