"""A faster, numerically equivalent rollout of the ``ours`` / ``cnn-lstm`` forward model.

The planner calls the forward model S = H x steps_per_horizon_step times in sequence per plan
(25 for N=50, H=5). Profiling ``ForcePredictor.predict`` in that loop (docs/planner.md) shows the
time goes to per-op overhead, not arithmetic: the LSTM of Eq. 11-16 is unrolled in Python
(~100 small ops for h = 10), three separate convolutions (Eq. 7), concatenations and the
normalisation. This module computes the same function with fewer ops:

* the three kernels (widths k_i, paddings p_i) become one convolution of width
  ``max(k_i + P - p_i)`` and padding ``P = max(p_i)``, each kernel placed at offset ``P - p_i``
  inside a zero kernel -- exactly the same sums;
* the attention weights (Eq. 9-10) scale the concatenated channels in one multiplication;
* the LSTM (Eq. 11-16) runs as torch's fused ``nn.LSTM`` with the gate rows reordered
  (this model's order f, i, g, o -> torch's i, f, g, o; its single bias as ``bias_ih``);
* the regressor's first layer is split into the LSTM-state part and the v_{k+1} part; the latter
  is computed for all S steps at once;
* the rollout buffer is kept in normalised units, so the force update of the increment head,
  ``F_{k+1} = F_k + out_mean + out_std * dF``, becomes one ``addcmul``.

The weights are read from the predictor on every :meth:`FusedConvAttentionLSTM.rollout`, so an
in-place update (MAML, Algorithm 1) or ``load_state_dict`` is picked up. ``test_planner_dynamics``
checks the result against ``predictor.predict`` step by step.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
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

    def __init__(self, predictor: Any, *, manual: bool = True) -> None:
        self.predictor = predictor
        self.manual = manual
        body = predictor.body
        self.h = int(predictor.h)
        convs = list(body.conv.convs)
        self.channels = convs[0].out_channels
        self.n_scales = len(convs)
        self.pad = max(int(c.padding[0]) for c in convs)
        self.width = max(int(c.kernel_size[0]) + self.pad - int(c.padding[0]) for c in convs)
        hidden = body.lstm.hidden
        dtype = predictor.in_mean.dtype
        self.lstm = nn.LSTM(self.channels * self.n_scales, hidden, batch_first=True, dtype=dtype)
        for p in self.lstm.parameters():
            p.requires_grad_(False)
        with torch.no_grad():
            self.lstm.bias_hh_l0.zero_()

    def _weights(self) -> dict[str, Any]:
        """The predictor's current weights, rearranged for the fused ops."""
        body = self.predictor.body
        convs = list(body.conv.convs)
        c_out, n_in = self.channels, convs[0].in_channels
        ref = convs[0].weight
        wc = torch.zeros((c_out * len(convs), n_in, self.width), dtype=ref.dtype)
        for i, conv in enumerate(convs):
            off = self.pad - int(conv.padding[0])
            k = int(conv.kernel_size[0])
            wc[i * c_out:(i + 1) * c_out, :, off:off + k] = conv.weight.detach()
        bc = torch.cat([conv.bias.detach() for conv in convs])
        lstm = body.lstm
        hid = lstm.hidden

        def reorder(w: torch.Tensor) -> torch.Tensor:  # f, i, g, o -> i, f, g, o
            return torch.cat([w[hid:2 * hid], w[:hid], w[2 * hid:]])

        self.lstm.weight_ih_l0.copy_(reorder(lstm.w_x.weight.detach()))
        self.lstm.bias_ih_l0.copy_(reorder(lstm.w_x.bias.detach()))
        self.lstm.weight_hh_l0.copy_(reorder(lstm.w_h.weight.detach()))
        # the convolution over a window as one dense [h*4, L*C_all] matrix (Toeplitz form)
        h, pad, width = self.h, self.pad, self.width
        length = h + 2 * pad - width + 1
        toe = torch.zeros((h, n_in, length, wc.shape[0]), dtype=ref.dtype)
        for j in range(length):
            for tap in range(width):
                row = j - pad + tap
                if 0 <= row < h:
                    toe[row, :, j, :] = wc[:, :, tap].t()
        # LSTM gates reordered f, i, g, o -> i, f, o, g: one sigmoid over the first 3 blocks
        def reorder_ifog(w: torch.Tensor) -> torch.Tensor:
            return torch.cat([w[hid:2 * hid], w[:hid], w[3 * hid:], w[2 * hid:3 * hid]])

        mlp = list(body.attention.mlp)
        reg = [m for m in body.regressor if isinstance(m, nn.Linear)]
        w1 = reg[0].weight.detach()
        return {
            "wc": wc, "bc": bc, "toe": toe.reshape(h * n_in, length * wc.shape[0]),
            "btoe": bc.repeat(length), "length": length,
            "wx_t": reorder_ifog(lstm.w_x.weight.detach()).t().contiguous(),
            "bx": reorder_ifog(lstm.w_x.bias.detach()),
            "wh_t": reorder_ifog(lstm.w_h.weight.detach()).t().contiguous(),
            "a1": (mlp[0].weight.detach(), mlp[0].bias.detach()),
            "a2": (mlp[2].weight.detach(), mlp[2].bias.detach()),
            "w1h_t": w1[:, :hid].t(), "w1v": w1[:, hid], "b1": reg[0].bias.detach(),
            "mid": [(m.weight.detach(), m.bias.detach()) for m in reg[1:]],
        }

    def rollout(self, window: np.ndarray, v: torch.Tensor, dt_s: float) -> torch.Tensor:
        """(q, fx, fz) [N, S, 3] from the last h rows ``window`` [h, 4] for ``v`` [N, S]."""
        p = self.predictor
        h = self.h
        n, s = v.shape
        dtype, dev = p.in_mean.dtype, p.in_mean.device
        wts = self._weights()
        in_mean, in_std = p.in_mean, p.in_std
        v = v.to(dtype=dtype, device=dev)
        base = torch.as_tensor(window, dtype=dtype, device=dev)
        bufn = torch.empty((n, h + s, 4), dtype=dtype, device=dev)
        bufn[:, :h] = (base - in_mean) / in_std
        q = base[-1, 0] + dt_s * torch.cumsum(v, dim=1)
        bufn[:, h:, 0] = (q - in_mean[0]) / in_std[0]
        vn = (v - in_mean[1]) / in_std[1]
        bufn[:, h:, 1] = vn
        vterm = torch.addcmul(wts["b1"], vn.unsqueeze(-1), wts["w1v"])  # [N, S, w1]
        shift = p.out_mean / in_std[2:4]
        scale = p.out_std / in_std[2:4]
        c, ns = self.channels, self.n_scales
        a1w, a1b = wts["a1"]
        a2w, a2b = wts["a2"]
        mid = wts["mid"]
        length, hid = wts["length"], self.predictor.body.lstm.hidden
        row = (h + s) * 4
        flat = bufn.view(n, row)
        a1w_t, a2w_t = a1w.t(), a2w.t()
        for k in range(s):
            if self.manual:
                x = flat.as_strided((n, h * 4), (row, 1), k * 4)
                z = torch.relu(torch.addmm(wts["btoe"], x, wts["toe"]))  # [N, L*C_all]
                zz = z.view(n * length, ns * c)
                a = torch.addmm(a2b, torch.tanh(torch.addmm(a1b, zz, a1w_t)), a2w_t)
                # softmax over the 3 scales (Eq. 9); torch.softmax is slow for a last dim of 3
                e = torch.exp(a - a.amax(dim=-1, keepdim=True))
                w = e / e.sum(dim=-1, keepdim=True)
                seq = (zz.view(n * length, ns, c) * w.unsqueeze(-1)).view(n * length, ns * c)
                zx = torch.addmm(wts["bx"], seq, wts["wx_t"]).view(n, length, 4 * hid)
                g = zx[:, 0]
                sg = torch.sigmoid(g[:, :3 * hid])
                cell = sg[:, :hid] * torch.tanh(g[:, 3 * hid:])
                h_t = sg[:, 2 * hid:3 * hid] * torch.tanh(cell)
                for t in range(1, length):
                    g = torch.addmm(zx[:, t], h_t, wts["wh_t"])
                    sg = torch.sigmoid(g[:, :3 * hid])
                    cell = torch.addcmul(sg[:, hid:2 * hid] * cell, sg[:, :hid],
                                         torch.tanh(g[:, 3 * hid:]))
                    h_t = sg[:, 2 * hid:3 * hid] * torch.tanh(cell)
                h_last = h_t
            else:
                x = bufn[:, k:k + h].transpose(1, 2)
                z = torch.relu(F.conv1d(x, wts["wc"], wts["bc"], padding=self.pad))
                z = z.transpose(1, 2)
                w = torch.softmax(F.linear(torch.tanh(F.linear(z, a1w, a1b)), a2w, a2b), dim=-1)
                seq = z * w.repeat_interleave(c, dim=-1) if ns > 1 else z * w
                h_last = self.lstm(seq)[1][0][0]
            y = torch.addmm(vterm[:, k], h_last, wts["w1h_t"])
            if mid:
                y = torch.relu(y)
                for wl, bl in mid[:-1]:
                    y = torch.relu(F.linear(y, wl, bl))
                y = F.linear(y, *mid[-1])
            d = y
            bufn[:, h + k, 2:4] = torch.addcmul(bufn[:, h + k - 1, 2:4] + shift, d, scale)
        forces = bufn[:, h:, 2:4] * in_std[2:4] + in_mean[2:4]
        return torch.cat([q.unsqueeze(-1), forces], dim=-1)
