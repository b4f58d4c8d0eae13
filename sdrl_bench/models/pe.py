"""A probabilistic ensemble (PE) dynamics model: K Gaussian MLPs in one ``torch.nn.Module``.

The model-based RL field's NN surrogate (PETS, Chua et al. 2018; MBPO, Janner et al. 2019; MOPO):
each member outputs a mean and a log-variance of the normalized state change; trained on the
Gaussian negative log-likelihood with learned, softly bounded log-variance limits (the limits
themselves pay a small penalty so that they stay tight); early stopping per member on the
validation MSE of its mean; the ``n_elites`` members with the best validation error are the
model (the others are dropped from prediction, as mbrl-lib's elites are).

Use in a surrogate: ``predict`` is the elites' mean (a deterministic step); ``sample`` draws one
step per row from a random elite's Gaussian (trajectory sampling "TS1": a member per step), which
the model env uses as its step noise in place of a measured dispersion; ``predict_members`` gives
the elites' means, whose disagreement is the same pessimism signal the SINDy ensemble gives.

Built on ``MLPDynamics`` (same normalization, optimizer, early stopping, persistence, hooks of
its training loop); mbrl-lib's ``GaussianMLP`` does the same with its own trainer, which would
bring its config system and Hydra version pins with it: hence written here on torch.nn.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sdrl_bench.models.mlp import EnsembleMLP
from sdrl_bench.models.nn import DTYPES, MLPDynamics, _check

LOGVAR_BOUND_PENALTY = 0.01
"""Weight of (sum of max log-variance - sum of min log-variance) in the loss (PETS)."""


class GaussianEnsembleMLP(nn.Module):
    """K MLPs with a Gaussian head: (K, N, 2 x out) = (mean, bounded log-variance)."""

    def __init__(self, sizes: list[int], k: int, activation: str, dtype: torch.dtype):
        super().__init__()
        self.n_out = sizes[-1]
        self.body = EnsembleMLP([*sizes[:-1], 2 * sizes[-1]], k, activation, dtype)
        self.max_logvar = nn.Parameter(torch.full((self.n_out,), 0.5, dtype=dtype))
        self.min_logvar = nn.Parameter(torch.full((self.n_out,), -10.0, dtype=dtype))

    def reset_parameters(self, gen: torch.Generator) -> None:
        self.body.reset_parameters(gen)
        with torch.no_grad():
            self.max_logvar.fill_(0.5)
            self.min_logvar.fill_(-10.0)

    def weights_and_biases(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """Weights (decayed) and the rest: biases and the log-variance bounds (not decayed)."""
        w, b = self.body.weights_and_biases()
        return w, [*b, self.max_logvar, self.min_logvar]

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        out = self.body(z)
        mean, raw = out[..., :self.n_out], out[..., self.n_out:]
        logvar = self.max_logvar - F.softplus(self.max_logvar - raw)
        logvar = self.min_logvar + F.softplus(logvar - self.min_logvar)
        return torch.cat([mean, logvar], dim=-1)


class GaussianEnsembleDynamics(MLPDynamics):
    """s_{t+1} = s_t + delta, delta ~ N(mean_k, var_k) of a random elite k (see the module doc).

    Parameters: those of ``MLPDynamics`` (``ensemble_size``: K members; ``noise_by`` is not
    used: the variance is learned), and ``n_elites`` (<= K) members kept for prediction.
    """

    kind = "pe"

    def __init__(self, n_elites: int = 5, ensemble_size: int = 7, width: int = 200, depth: int = 3,
                 activation: str = "silu", **kwargs: Any):
        kwargs.pop("noise_by", None)
        super().__init__(ensemble_size=ensemble_size, width=width, depth=depth, activation=activation, **kwargs)
        _check(isinstance(n_elites, int) and not isinstance(n_elites, bool) and 1 <= n_elites <= ensemble_size,
               "n_elites", f"must be an integer in [1, ensemble_size = {ensemble_size}]", n_elites)
        self.n_elites = n_elites
        self.elites_ = np.arange(n_elites)

    def hyperparameters(self) -> dict[str, Any]:
        out = super().hyperparameters()
        out.pop("noise_by", None)
        return {**out, "n_elites": self.n_elites}

    def network(self, n_in: int, n_out: int) -> GaussianEnsembleMLP:
        return GaussianEnsembleMLP(self.layer_sizes(n_in, n_out), self.ensemble_size, self.activation,
                                   DTYPES[self.dtype])

    # ------------------------------------------------------------------ training hooks
    def _train_loss(self, out: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        n = y.shape[-1]
        mean, logvar = out[..., :n], out[..., n:]
        nll = ((mean - y) ** 2 * torch.exp(-logvar) + logvar).mean(dim=(1, 2))
        net = self.net_
        bounds = LOGVAR_BOUND_PENALTY * (net.max_logvar.sum() - net.min_logvar.sum())
        return nll + bounds / len(nll)  # summed over members by the loop: the bounds' penalty once

    def _means(self, out: torch.Tensor) -> torch.Tensor:
        return out[..., :out.shape[-1] // 2]

    def _after_fit(self) -> None:
        self.elites_ = np.sort(np.argsort(np.asarray(self.best_val_loss_))[:self.n_elites])

    # ------------------------------------------------------------------ use
    def _outputs(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        z = np.concatenate([np.atleast_2d(x), np.atleast_2d(u)], axis=1)
        zn = (z - self.input_mean_) / self.input_std_
        with torch.inference_mode():
            out = self.net_(torch.from_numpy(zn.astype(self._np_dtype, copy=False))).numpy()
        return out[self.elites_].astype(float)

    def predict_members(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Each elite's mean next state, (n_elites, N, n_states)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        out = self._outputs(x, u)
        return x + out[..., :x.shape[1]] * self.output_std_ + self.output_mean_

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The elites' mean next state (N, n_states)."""
        return self.predict_members(x, u).mean(axis=0)

    def sample(self, x: np.ndarray, u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One next state per row (N, n_states) drawn from a random elite's Gaussian."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        out, n = self._outputs(x, u), x.shape[1]
        pick = rng.integers(len(out), size=len(x))
        rows = np.arange(len(x))
        mean, logvar = out[pick, rows, :n], out[pick, rows, n:]
        delta = mean + np.exp(0.5 * logvar) * rng.standard_normal(mean.shape)
        return x + delta * self.output_std_ + self.output_mean_

    def predict_std(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The elites' disagreement (std of their means) per state, (N, n_states)."""
        return self.predict_members(x, u).std(axis=0)

    def summary_metrics(self) -> dict[str, float]:
        return {**super().summary_metrics(), "pe_n_elites": float(self.n_elites)}

    def describe(self) -> str:
        return (super().describe().replace("MLP", "Gaussian MLP", 1)
                + f"elites (best validation MSE): members {self.elites_.tolist()} of {self.ensemble_size}\n")
