"""The network of the NN baseline as a ``torch.nn.Module``: an ensemble of K MLPs in one.

``EnsembleLinear`` holds K affine maps as stacked parameters, ``weight`` (K, fan_in, fan_out) and
``bias`` (K, fan_out), and applies them in one batched matmul (the pattern of mbrl-lib's
``EnsembleLinearLayer``). ``EnsembleMLP`` stacks them with an activation between layers. Its
state dict keys are ``layers.<i>.weight`` / ``layers.<i>.bias``, the keys of the files saved
before the network was a module, so those files load unchanged (``load_state_dict(strict=True)``
checks the keys and shapes).

Numerics are those of the hand-written forward it replaces: one member fed a 2-D batch runs plain
2-D GEMMs (``addmm``); otherwise (N, in) or (K, N, in) inputs broadcast against the stacked
weights. Initialization draws, layer by layer, weight then bias, uniform in +-1/sqrt(fan_in) in
float64 from the given generator, then casts to the network's dtype.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

ACTIVATIONS = {"tanh": torch.tanh, "relu": F.relu, "silu": F.silu, "elu": F.elu, "gelu": F.gelu}


class EnsembleLinear(nn.Module):
    """K independent affine maps ``h @ weight[k] + bias[k]``."""

    def __init__(self, k: int, fan_in: int, fan_out: int, dtype: torch.dtype):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(k, fan_in, fan_out, dtype=dtype))
        self.bias = nn.Parameter(torch.empty(k, fan_out, dtype=dtype))

    @torch.no_grad()
    def reset_parameters(self, gen: torch.Generator) -> None:
        bound = 1.0 / np.sqrt(self.weight.shape[1])
        for p in (self.weight, self.bias):
            p.copy_((torch.rand(p.shape, generator=gen, dtype=torch.float64) * 2 - 1) * bound)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """(N, in) or (K, N, in) -> (K, N, out); (N, in) -> (N, out) when K = 1."""
        if h.dim() == 2 and self.weight.shape[0] == 1:
            return torch.addmm(self.bias[0], h, self.weight[0])
        return torch.matmul(h, self.weight) + self.bias.unsqueeze(1)


class EnsembleMLP(nn.Module):
    """K MLPs of layer sizes ``sizes`` (inputs, hidden..., outputs), run together."""

    def __init__(self, sizes: list[int], k: int, activation: str, dtype: torch.dtype):
        super().__init__()
        self.layers = nn.ModuleList(
            EnsembleLinear(k, a, b, dtype) for a, b in zip(sizes[:-1], sizes[1:], strict=True))
        self.act = ACTIVATIONS[activation]

    def reset_parameters(self, gen: torch.Generator) -> None:
        for layer in self.layers:
            layer.reset_parameters(gen)

    def weights_and_biases(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """The layers' weights and biases, apart (AdamW decays the weights only)."""
        return [layer.weight for layer in self.layers], [layer.bias for layer in self.layers]

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """(N, in) or (K, N, in) normalized inputs -> (K, N, out) normalized deltas."""
        h = z
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < last:
                h = self.act(h)
        return h if h.dim() == 3 else h.unsqueeze(0)
