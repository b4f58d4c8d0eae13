"""Neural-network dynamics baseline: an MLP (or an ensemble of K MLPs) in torch.

Each member maps normalized inputs (s_t, c_t) to the normalized change s_{t+1} - s_t; the
prediction is s_t plus the de-normalized member mean. Normalization statistics (mean, std per
input and per output column) come from the training rows. Training: AdamW (weight decay on the
weights, not the biases) on the normalized-delta MSE, mini-batches reshuffled every epoch,
early stopping on a held-out validation split (each member keeps its best-validation weights).

The network is a ``torch.nn.Module`` (``models.mlp.EnsembleMLP``): the K members are stacked
parameters (layer weight ``(K, fan_in, fan_out)``), so the whole ensemble trains and predicts in
one batched matmul per layer. Members differ by their initialization and mini-batch order; they
share the train / validation split.

Numerics: the network runs in ``dtype`` (float32 by default); normalization, de-normalization
and the residual ``s_t + delta`` are float64 numpy. Same seed, same thread count -> bitwise-equal
weights and predictions. The model saves as data: JSON metadata plus a tensor-only state dict.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np
import torch

from sdrl_bench import ConfigError
from sdrl_bench.models import nn_io
from sdrl_bench.models.base import read_model_json, residual_noise
from sdrl_bench.models.mlp import ACTIVATIONS, EnsembleMLP

DTYPES = {"float32": torch.float32, "float64": torch.float64}
KEY = "surrogate.model"


def _check(ok: bool, key: str, message: str, value: Any) -> None:
    if not ok:
        raise ConfigError(f"{KEY}.{key} {message}, got {value!r}")


class MLPDynamics:
    """s_{t+1} = s_t + MLP(normalized s_t, c_t), optionally an ensemble of K MLPs.

    Parameters
    ----------
    width, depth : hidden units per layer and number of hidden layers.
    activation : one of ``ACTIVATIONS``.
    learning_rate, weight_decay : AdamW settings (decay on weights only).
    max_epochs, max_steps : training stops at whichever comes first (``max_steps`` None: no cap).
    batch_size : rows per gradient step (capped at the number of training rows).
    val_fraction : share of the fit rows held out for early stopping (at least one row).
    patience : epochs without a better validation loss before a member stops improving; training
        ends when every member has run out of patience.
    ensemble_size : K members; ``predict`` is their mean, ``predict_std`` their spread.
    dtype : "float32" or "float64", the network's arithmetic.
    num_threads : torch threads during ``fit`` (restored afterwards); None leaves torch's setting.
    seed : seeds the split, the initialization and the mini-batch order.
    noise_by : one-hot controls whose steps carry random dispersion: the fit measures the step
        noise (``noise_``: residual covariance per control) as SINDy's per-equation model does,
        so both surrogates step with the same kind of noise.
    """

    kind = "nn"
    summary_file = "architecture.txt"

    def __init__(self, width: int = 64, depth: int = 2, activation: str = "tanh",
                 learning_rate: float = 1e-3, weight_decay: float = 0.0, max_epochs: int = 2000,
                 max_steps: int | None = 4000, batch_size: int = 64, val_fraction: float = 0.2,
                 patience: int = 200, ensemble_size: int = 1, dtype: str = "float32",
                 num_threads: int | None = 1, seed: int = 0, noise_by: Sequence[str] = ()):
        for key, value in (("width", width), ("depth", depth), ("max_epochs", max_epochs),
                           ("batch_size", batch_size), ("patience", patience),
                           ("ensemble_size", ensemble_size)):
            _check(isinstance(value, int) and not isinstance(value, bool) and value > 0,
                   key, "must be a positive integer", value)
        _check(max_steps is None or (isinstance(max_steps, int) and max_steps > 0),
               "max_steps", "must be a positive integer or null", max_steps)
        _check(num_threads is None or (isinstance(num_threads, int) and num_threads > 0),
               "num_threads", "must be a positive integer or null", num_threads)
        _check(activation in ACTIVATIONS, "activation", f"must be one of {sorted(ACTIVATIONS)}", activation)
        _check(dtype in DTYPES, "dtype", f"must be one of {sorted(DTYPES)}", dtype)
        _check(isinstance(learning_rate, (int, float)) and 0 < learning_rate < np.inf,
               "learning_rate", "must be positive", learning_rate)
        _check(isinstance(weight_decay, (int, float)) and 0 <= weight_decay < np.inf,
               "weight_decay", "must be >= 0", weight_decay)
        _check(isinstance(val_fraction, (int, float)) and 0 < val_fraction < 1,
               "val_fraction", "must be in (0, 1)", val_fraction)
        _check(isinstance(seed, int) and not isinstance(seed, bool), "seed", "must be an integer", seed)
        self.width, self.depth, self.activation = width, depth, activation
        self.learning_rate, self.weight_decay = float(learning_rate), float(weight_decay)
        self.max_epochs, self.max_steps, self.batch_size = max_epochs, max_steps, batch_size
        self.val_fraction, self.patience, self.ensemble_size = float(val_fraction), patience, ensemble_size
        self.dtype, self.num_threads, self.seed = dtype, num_threads, seed
        self.noise_by = tuple(str(c) for c in (noise_by or ()))
        self.noise_: dict[str, list] = {}

    # ------------------------------------------------------------------ structure
    def hyperparameters(self) -> dict[str, Any]:
        """The constructor arguments, as saved in the metadata."""
        keys = ("width", "depth", "activation", "learning_rate", "weight_decay", "max_epochs",
                "max_steps", "batch_size", "val_fraction", "patience", "ensemble_size", "dtype",
                "num_threads", "seed")
        return {**{k: getattr(self, k) for k in keys}, "noise_by": list(self.noise_by)}

    def layer_sizes(self, n_in: int, n_out: int) -> list[int]:
        return [n_in] + [self.width] * self.depth + [n_out]

    def network(self, n_in: int, n_out: int) -> EnsembleMLP:
        """An uninitialized network of this architecture (``fit`` initializes it, loading fills it)."""
        return EnsembleMLP(self.layer_sizes(n_in, n_out), self.ensemble_size, self.activation, DTYPES[self.dtype])

    @property
    def n_parameters(self) -> int:
        """Trainable scalars over all members."""
        return int(sum(t.numel() for t in self.net_.parameters()))

    # ------------------------------------------------------------------ fit
    def fit(self, x: np.ndarray, u: np.ndarray, x_next: np.ndarray, *,
            state_names: Sequence[str], control_names: Sequence[str],
            bounds: dict[str, tuple[float, float]] | None = None) -> MLPDynamics:
        """Fit on rows (x_t, u_t) -> x_{t+1} (rows independent; ``bounds`` not used: the
        surrogate bounds every prediction)."""
        x, u, x_next = (np.asarray(a, dtype=float) for a in (x, u, x_next))
        if x.shape[1] != len(state_names) or u.shape[1] != len(control_names) or x_next.shape != x.shape:
            raise ValueError("x / u / x_next columns do not match state_names / control_names")
        if len(x) < 2:
            raise ConfigError(f"{KEY}: the NN needs at least 2 rows (train + validation), got {len(x)}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(u)) and np.all(np.isfinite(x_next))):
            raise ValueError("non-finite values in the training rows")
        unknown = [c for c in self.noise_by if c not in control_names]
        _check(not unknown, "noise_by", f"names controls that are not inputs ({', '.join(control_names)})", unknown)
        _warm_up()
        prev_threads = torch.get_num_threads()
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            if self.num_threads is not None:
                torch.set_num_threads(self.num_threads)
            self._fit(np.concatenate([x, u], axis=1), x_next - x, list(state_names), list(control_names))
        finally:
            torch.set_num_threads(prev_threads)
        # the step noise as SINDy's per-equation model measures it: residual covariances per control
        self.noise_ = residual_noise(x_next - self.predict(x, u), u, self.control_names_, self.noise_by)
        self.fit_wall_seconds_ = time.perf_counter() - t0
        self.fit_cpu_seconds_ = time.process_time() - c0
        self.n_fit_samples_ = len(x)
        return self

    def _fit(self, z: np.ndarray, dz: np.ndarray, state_names: list[str], control_names: list[str]) -> None:
        self.state_names_, self.control_names_ = state_names, control_names
        self.input_mean_, self.input_std_ = _stats(z)
        self.output_mean_, self.output_std_ = _stats(dz)
        n = len(z)
        n_val = min(n - 1, max(1, int(round(self.val_fraction * n))))
        order = np.random.default_rng(self.seed).permutation(n)
        val, train = order[:n_val], order[n_val:]
        self.n_train_rows_, self.n_val_rows_ = len(train), len(val)
        dt = DTYPES[self.dtype]
        zn = torch.from_numpy((z - self.input_mean_) / self.input_std_).to(dt)
        yn = torch.from_numpy((dz - self.output_mean_) / self.output_std_).to(dt)
        z_tr, y_tr, z_va, y_va = zn[train], yn[train], zn[val], yn[val]
        gen = torch.Generator().manual_seed(self.seed)
        net = self.net_ = self.network(z.shape[1], dz.shape[1])
        net.reset_parameters(gen)
        params = list(net.parameters())
        weights, biases = net.weights_and_biases()
        opt = torch.optim.AdamW([{"params": weights, "weight_decay": self.weight_decay},
                                 {"params": biases, "weight_decay": 0.0}], lr=self.learning_rate, fused=True)
        k, batch = self.ensemble_size, min(self.batch_size, len(train))
        best = torch.full((k,), float("inf"), dtype=torch.float64)
        best_params = [p.detach().clone() for p in params]
        best_epoch, since = torch.zeros(k, dtype=torch.long), torch.zeros(k, dtype=torch.long)
        steps = epoch = 0
        while epoch < self.max_epochs and (self.max_steps is None or steps < self.max_steps):
            perm = torch.argsort(torch.rand(k, len(train), generator=gen), dim=1)
            for start in range(0, len(train) - batch + 1, batch):  # drop a ragged tail batch
                idx = perm[:, start:start + batch]
                loss = self._train_loss(net(z_tr[idx]), y_tr[idx]).sum()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                steps += 1
                if self.max_steps is not None and steps >= self.max_steps:
                    break
            epoch += 1
            with torch.no_grad():
                val_loss = self._val_loss(net(z_va), y_va).to(torch.float64)
                better = val_loss < best
                best = torch.where(better, val_loss, best)
                best_epoch = torch.where(better, epoch, best_epoch)
                since = torch.where(better, 0, since + 1)
                if bool(better.all()):
                    for saved, p in zip(best_params, params, strict=True):
                        saved.copy_(p)
                elif bool(better.any()):
                    for saved, p in zip(best_params, params, strict=True):
                        if p.dim() and p.shape[0] == k:  # per member
                            saved[better] = p[better]
                        else:  # shared by the members (a Gaussian head's log-variance bounds)
                            saved.copy_(p)
            if bool(torch.all(since >= self.patience)):
                break
        net.requires_grad_(False)
        with torch.no_grad():
            for p, saved in zip(params, best_params, strict=True):
                p.copy_(saved)
        self.epochs_run_, self.steps_run_ = epoch, steps
        self.best_val_loss_ = best.numpy().copy()
        self.best_epoch_ = best_epoch.numpy().copy()
        with torch.inference_mode():
            spread = self._means(net(z_va)).std(dim=0, unbiased=False).mean() if k > 1 else torch.zeros(())
        self.val_member_std_ = float(spread)
        self._after_fit()

    # hooks of the training loop (a probabilistic ensemble overrides them: ``models.pe``)
    def _train_loss(self, out: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Per-member training loss (K,): the normalized-delta MSE."""
        return ((out - y) ** 2).mean(dim=(1, 2))

    def _val_loss(self, out: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Per-member validation loss (K,) for early stopping: the normalized-delta MSE."""
        return ((self._means(out) - y) ** 2).mean(dim=(1, 2))

    def _means(self, out: torch.Tensor) -> torch.Tensor:
        """The members' predicted normalized deltas from the network's output."""
        return out

    def _after_fit(self) -> None:
        """Called once the best weights are restored."""

    # ------------------------------------------------------------------ use
    def predict_members(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Each member's next regressed states, (K, N, n_states), float64."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        out = self._normalized_deltas(x, u)
        return x + (out.astype(float) * self.output_std_ + self.output_mean_)

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next regressed states (N, n_states) for states (N, n_states) and controls (N, n_controls):
        the member mean, float64."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        out = self._normalized_deltas(x, u)
        mean = out[0].astype(float) if len(out) == 1 else out.mean(axis=0, dtype=np.float64)
        return x + (mean * self.output_std_ + self.output_mean_)

    def predict_std(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Member disagreement per state (N, n_states): the std over members (zeros for K = 1)."""
        members = self.predict_members(x, u)
        return members.std(axis=0)

    def _normalized_deltas(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        z = np.concatenate([x, np.atleast_2d(u)], axis=1)
        zn = (z - self.input_mean_) / self.input_std_
        with torch.inference_mode():
            return self._means(self.net_(torch.from_numpy(zn.astype(self._np_dtype, copy=False)))).numpy()

    @property
    def _np_dtype(self) -> type:
        return np.float32 if self.dtype == "float32" else np.float64

    def summary_metrics(self) -> dict[str, float]:
        return {
            "n_parameters": float(self.n_parameters),
            "nn_epochs_run": float(self.epochs_run_),
            "nn_steps_run": float(self.steps_run_),
            "nn_best_val_loss": float(np.mean(self.best_val_loss_)),
            "nn_best_epoch": float(np.max(self.best_epoch_)),
            "nn_ensemble_size": float(self.ensemble_size),
            "nn_val_member_std": self.val_member_std_,
        }

    def describe(self) -> str:
        """Architecture, training and its outcome, as text."""
        sizes = " -> ".join(str(s) for s in self.layer_sizes(len(self.input_mean_), len(self.output_mean_)))
        inputs = ", ".join(self.state_names_ + self.control_names_)
        members = f"ensemble of {self.ensemble_size} MLPs" if self.ensemble_size > 1 else "MLP"
        return (
            f"{members} {sizes} ({self.activation}, {self.dtype}); predicts s[k+1] - s[k] of "
            f"({', '.join(self.state_names_)}) from normalized ({inputs})\n"
            f"parameters: {self.n_parameters}\n"
            f"AdamW lr {self.learning_rate:g}, weight decay {self.weight_decay:g}, batch {self.batch_size}, "
            f"seed {self.seed}; {self.n_train_rows_} train / {self.n_val_rows_} validation rows\n"
            f"trained {self.epochs_run_} epochs ({self.steps_run_} steps; max {self.max_epochs} epochs, "
            f"{self.max_steps} steps, patience {self.patience}); best validation MSE (normalized) "
            f"{np.mean(self.best_val_loss_):.4g} at epoch {int(np.max(self.best_epoch_))}\n"
        )

    # ------------------------------------------------------------------ persistence (data only)
    def save(self, path: str | Path) -> Path:
        """Write ``path`` (JSON metadata) and ``<stem>.pt`` beside it (a tensor-only state dict)."""
        return nn_io.save(self, Path(path))

    @classmethod
    def from_saved(cls, data: dict, path: Path) -> MLPDynamics:
        """The loader ``models.base.load_model`` calls with the JSON object of ``path``; a weights
        file that does not match the metadata raises ConfigError."""
        return nn_io.load(cls, data, Path(path))

    @classmethod
    def load(cls, path: str | Path) -> MLPDynamics:
        """Load a saved model; a weights file that does not match the metadata raises ConfigError."""
        return cls.from_saved(read_model_json(path), Path(path))


@functools.cache
def _warm_up() -> None:
    """The first optimizer built in a process imports torch's compiler stack (about 1 s); done
    once, outside the timed fit, as pysindy's import is outside SINDy's."""
    torch.optim.AdamW([torch.zeros(1, requires_grad=True)], fused=True)


def _stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column mean and std (a constant column gets std 1)."""
    std = a.std(axis=0)
    return a.mean(axis=0), np.where(std > 0, std, 1.0)
