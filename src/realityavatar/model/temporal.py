"""Temporal modules over the window of pose features f_p: LSTM/GRU (output at the current frame) or none."""

from __future__ import annotations

import torch
from torch import nn


class RecurrentTemporal(nn.Module):
    """A recurrent network (the subclass's `cell`) over f_p [B,T,D] (oldest first); h_t is the output at the last
    (current) time step. Its weights are `rnn.*` for either cell."""

    cell: type[nn.RNNBase]

    def __init__(self, in_dim: int, hidden_dim: int, num_layers: int):
        super().__init__()
        self.rnn = self.cell(in_dim, hidden_dim, num_layers=num_layers, batch_first=True)
        self.out_dim = hidden_dim

    def forward(self, f_p: torch.Tensor) -> torch.Tensor:
        """f_p [B,T,D] -> h_t [B,hidden_dim]."""
        out, _ = self.rnn(f_p)
        return out[:, -1]

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"temporal": list(self.parameters())}


class LSTMTemporal(RecurrentTemporal):
    """The paper's temporal module, an LSTM (temporal=lstm)."""

    cell = nn.LSTM


class GRUTemporal(RecurrentTemporal):
    """A GRU in the LSTM's place (temporal=gru)."""

    cell = nn.GRU


class NoTemporal(nn.Module):
    """Ablation 'no temporal module': uses only the current frame f_p[:, -1] through a Linear+SiLU of the same width."""

    def __init__(self, in_dim: int, hidden_dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.SiLU())
        self.out_dim = hidden_dim

    def forward(self, f_p: torch.Tensor) -> torch.Tensor:
        """f_p [B,T,D] -> h_t [B,hidden_dim]; frames before the last are ignored."""
        return self.net(f_p[:, -1])

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"temporal": list(self.parameters())}
