"""Network bodies of the forward model f_theta(x_t, v_t) (paper 3.1, Fig. 4-5) and baselines (4.3).

All modules here work on *normalised* tensors; :class:`~peel_model.predictor.ForcePredictor`
wraps them with the normalisation and the paper units. Input ``x``: ``[B, h, 4]`` with the columns
``[q, v, fx, fz]`` of samples k-h+1..k (Eq. 2); ``v_next``: ``[B]``, the velocity v_{k+1} about
to be applied; output ``[B, 2]``: the normalised force increment (see the predictor).

Design decisions (the paper is ambiguous here; each choice with its reason):

* **The "3 rows" of the 3 x k kernels.** Eq. 2 has three physical series (q, v, F) but F has two
  components (F_RX, F_RZ), so x_t has four rows. The kernels are 1D convolutions over time whose
  height spans *all* input rows, i.e. ``Conv1d(in_channels=4, kernel_size=k)``: the paper's 3 x k
  is "every physical row x k samples", which with a two-component force is 4 x k. Keeping both
  force components lets every kernel see the stick-slip coupling between F_RX and F_RZ.
* **Equal lengths.** Widths 2, 4, 6 with paddings 0, 1, 2 and stride 1 give output lengths
  h+2p-k+1 = h-1 for all three (3.1.1); :meth:`ModelConfig.check` verifies it for any config.
* **What S1, S2, S3 are.** Fig. 4 names S1..S3 the outputs of the three kernels, so attention
  weights the three *scales* (Eq. 8-10). The weights are computed per time step
  (o_t = MLP([S1_t, S2_t, S3_t]), Eq. 8 carries the index t) and sum to 1 over the scales (Eq. 9).
  The weighted sequences are concatenated (Eq. 10) and fed to the LSTM.
* **LSTM** written out with the gates of Eq. 11-16 (sigmoid output gate; Eq. 15's "softmax" is a
  typo for sigma) rather than ``torch.nn.LSTM``: plain tensor ops with no in-place updates or fused
  kernels, so ``torch.func.functional_call`` and second-order gradients (MAML, Eq. 26-27) work on
  CPU and CUDA alike. Its last hidden state summarises the history.
* **Regressor.** [LSTM state, v_{k+1}] -> FC 128-64-32-16 with ReLU -> linear head (3.1.3).
* **Baselines (4.3).** ``mlp``: the same regressor on the flattened history. ``cnn-lstm``: one
  kernel size (width 4, padding 1) in three branches, attention and everything else identical, so
  the only difference to ``ours`` is the multi-scale kernel set (the paper's "single-size
  convolution kernel ... other settings (including the attention mechanism) consistent"); with a
  single branch the softmax over one weight would be identically 1, i.e. no attention at all.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .config import ModelConfig

N_INPUTS = 4  # [q, v, fx, fz] (Eq. 2)
N_OUTPUTS = 2  # [fx, fz] at k+1


def _regressor(n_in: int, widths: tuple[int, ...]) -> nn.Sequential:
    """FC layers with ReLU (3.1.3) followed by a linear head to the two forces."""
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Linear(n_in, w), nn.ReLU()]
        n_in = w
    layers.append(nn.Linear(n_in, N_OUTPUTS))
    return nn.Sequential(*layers)


class MultiScaleConv(nn.Module):
    """Parallel 1D convolutions over time, one per kernel width (3.1.1, Eq. 7), with ReLU."""

    def __init__(self, h: int, channels: int, kernels: tuple[int, ...], paddings: tuple[int, ...]):
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv1d(N_INPUTS, channels, k, stride=1, padding=p)
            for k, p in zip(kernels, paddings, strict=True)
        )
        self.out_len = h + 2 * paddings[0] - kernels[0] + 1

    def forward(self, x: Tensor) -> list[Tensor]:
        """``x``: ``[B, h, 4]`` -> list of S_i, each ``[B, out_len, channels]``."""
        xc = x.transpose(1, 2)
        return [torch.relu(conv(xc)).transpose(1, 2) for conv in self.convs]


class ScaleAttention(nn.Module):
    """o_t = MLP([S1_t, S2_t, S3_t]) (Eq. 8), w = softmax(o_t) (Eq. 9), S_i' = w_i S_i (Eq. 10)."""

    def __init__(self, n_scales: int, channels: int, hidden: int):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(n_scales * channels, hidden), nn.Tanh(), nn.Linear(hidden, n_scales)
        )

    def forward(self, scales: list[Tensor]) -> tuple[Tensor, Tensor]:
        """-> (concatenated weighted sequences ``[B, L, n*C]``, weights ``[B, L, n]``)."""
        cat = torch.cat(scales, dim=-1)
        w = torch.softmax(self.mlp(cat), dim=-1)
        weighted = [w[..., i : i + 1] * s for i, s in enumerate(scales)]
        return torch.cat(weighted, dim=-1), w


class LSTM(nn.Module):
    """One LSTM layer, Eq. 11-16, unrolled over the sequence; returns the last hidden state."""

    def __init__(self, n_in: int, hidden: int):
        super().__init__()
        self.hidden = hidden
        self.w_x = nn.Linear(n_in, 4 * hidden)  # input part of W_{f,i,g,o} [h_{t-1}, x_t] + b
        self.w_h = nn.Linear(hidden, 4 * hidden, bias=False)  # recurrent part

    def forward(self, seq: Tensor) -> Tensor:
        """``seq``: ``[B, L, n_in]`` -> h_L ``[B, hidden]``."""
        b, length, _ = seq.shape
        zx = self.w_x(seq)
        h = seq.new_zeros(b, self.hidden)
        c = seq.new_zeros(b, self.hidden)
        for t in range(length):
            z = zx[:, t] + self.w_h(h)
            f, i, g, o = z.chunk(4, dim=-1)  # gate order f, i, g, o (fused copies rely on it)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)  # Eq. 11, 12, 13, 14
            h = torch.sigmoid(o) * torch.tanh(c)  # Eq. 15, 16
        return h


class ConvAttentionLSTM(nn.Module):
    """``ours`` (multi-scale kernels) and ``cnn-lstm`` (one kernel size): Fig. 5."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        if cfg.arch == "ours":
            kernels, paddings = cfg.kernels, cfg.paddings
        else:
            kernels, paddings = cfg.cnn_lstm_kernels, cfg.cnn_lstm_paddings
        self.conv = MultiScaleConv(cfg.h, cfg.conv_channels, kernels, paddings)
        n = len(kernels)
        self.attention = ScaleAttention(n, cfg.conv_channels, cfg.attention_hidden)
        self.lstm = LSTM(n * cfg.conv_channels, cfg.lstm_hidden)
        self.regressor = _regressor(cfg.lstm_hidden + 1, cfg.fc)

    def features(self, x: Tensor) -> tuple[list[Tensor], Tensor, Tensor]:
        """-> (scale outputs S_i, attention weights ``[B, L, n]``, LSTM state ``[B, H]``)."""
        scales = self.conv(x)
        weighted, w = self.attention(scales)
        return scales, w, self.lstm(weighted)

    def forward(self, x: Tensor, v_next: Tensor) -> Tensor:
        _, _, state = self.features(x)
        return self.regressor(torch.cat([state, v_next.unsqueeze(-1)], dim=-1))


class MLPBody(nn.Module):
    """``mlp`` baseline (4.3): the same regressor on the flattened history and v_{k+1}."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.regressor = _regressor(cfg.h * N_INPUTS + 1, cfg.fc)

    def forward(self, x: Tensor, v_next: Tensor) -> Tensor:
        return self.regressor(torch.cat([x.flatten(1), v_next.unsqueeze(-1)], dim=-1))


def build_body(cfg: ModelConfig) -> nn.Module:
    """The network body for ``cfg.arch``."""
    cfg.check()
    if cfg.arch == "mlp":
        return MLPBody(cfg)
    return ConvAttentionLSTM(cfg)
