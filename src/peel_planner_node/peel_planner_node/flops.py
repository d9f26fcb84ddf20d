"""Multiply-adds of one model step per sample: of the model as defined, and of the fused rollout.

``peel bench planner`` divides the multiply-adds of a plan (N x S model steps) by the measured
peak of a torch matmul on the machine to report the FLOP-limited floor of a plan's latency
(docs/planner.md). Only matrix products count (convolution, attention MLP, LSTM gates,
regressor); the elementwise ops (sigmoid, tanh, the cell update) are not multiply-adds.
"""

from __future__ import annotations

from typing import Any

from torch import nn


def model_macs_per_step(predictor: Any) -> int:
    """Multiply-adds of one ``predictor.predict`` for one sample, as the model defines it (each
    kernel over each of the L window positions, the LSTM over L positions)."""
    body = predictor.body
    linears = [m for m in body.regressor if isinstance(m, nn.Linear)]
    macs = sum(m.in_features * m.out_features for m in linears)
    if not hasattr(body, "lstm"):  # the mlp baseline: the regressor is all
        return macs
    convs = list(body.conv.convs)
    length = body.conv.out_len
    mlp = [m for m in body.attention.mlp if isinstance(m, nn.Linear)]
    per_position = (sum(c.in_channels * c.out_channels * c.kernel_size[0] for c in convs)
                    + sum(m.in_features * m.out_features for m in mlp)
                    + body.lstm.w_x.in_features * body.lstm.w_x.out_features
                    + body.lstm.w_h.in_features * body.lstm.w_h.out_features)
    return macs + length * per_position


def fused_macs_per_step(predictor: Any) -> int:
    """Multiply-adds of one model step of the fused rollout for one sample, in the steady state
    (D windows in flight; dense Toeplitz zeros and the ones columns included)."""
    from .fused_weights import Schedule, rearrange

    sch = Schedule.of(predictor)
    w = rearrange(predictor, sch)
    nw, c_all, hid = len(sch.wave), sch.conv_width, sch.hidden
    macs = w.conv_wave.shape[0] * w.conv_wave.shape[1]  # Toeplitz conv of the wavefront
    macs += nw * (w.att1_weight_t.numel() + w.att2_weight_t.numel())  # attention MLP
    macs += nw * sch.n_scales * c_all  # scale weights expanded over the channels
    macs += nw * (c_all + 1) * 4 * hid  # W_x x + b of the wavefront positions
    macs += (sch.depth + sch.pad) * hid * 4 * hid  # W_h h: in-flight block + bottom edges
    macs += w.fc1_h_t.numel() + sum(t.numel() for t in w.fc_layers)  # regressor
    return int(macs)
