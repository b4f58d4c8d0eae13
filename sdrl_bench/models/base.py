"""The protocol every dynamics model follows, and loading a saved model by its kind.

Loading goes through a registry, ``{kind: "module:Class"}``: this module imports no concrete
model (the models import it), and a class is imported only when a file of its kind is loaded,
so torch loads only when an NN is used. A new kind of model registers itself with
``register_loader``; its class provides ``from_saved(data, path)``.
"""

from __future__ import annotations

import contextlib
import importlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol, runtime_checkable
from collections.abc import Sequence

import numpy as np

from sdrl_bench import ConfigError


@contextlib.contextmanager
def seeded_global_numpy(seed: int | None) -> Iterator[None]:
    """numpy's global random state seeded with ``seed`` inside, restored after: pysindy's
    ``EnsembleOptimizer`` draws its bootstrap rows and library subsets from ``np.random``, which
    no argument seeds, so a fit with it is reproducible only this way."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(saved)


@runtime_checkable
class DynamicsModel(Protocol):
    """s_{t+1} = f(s_t, c_t) over regressed states s and controls c (actions, exogenous states).

    Estimator contract: ``__init__`` validates and stores hyperparameters, ``fit`` returns self
    and sets the ``_``-suffixed learned attributes (including ``fit_wall_seconds_`` and
    ``fit_cpu_seconds_``). ``save(path)`` writes ``path`` (JSON metadata) and any sibling files
    (weights as a state dict): data, never a pickle.
    """

    kind: str
    summary_file: str

    def fit(self, x: np.ndarray, u: np.ndarray, x_next: np.ndarray, *,
            state_names: Sequence[str], control_names: Sequence[str],
            bounds: dict[str, tuple[float, float]] | None = None) -> DynamicsModel: ...
    """``bounds``: the env's bounds per regressed state (``EnvSpec.target_bounds``); a model
    that composes next values from others (a per-equation model's primed terms) applies them in
    between, as the env does; others may ignore them (the surrogate bounds every prediction)."""

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...

    def save(self, path: str | Path) -> Path: ...

    def summary_metrics(self) -> dict[str, float]: ...

    def describe(self) -> str: ...


def read_model_json(path: str | Path) -> dict:
    """The JSON object of a saved model file; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model file not found: {path}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not a valid model file (not JSON: {exc})") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a valid model file (not a JSON object)")
    return data


def write_model_json(path: str | Path, data: dict) -> Path:
    """Write a model file (``read_model_json``'s counterpart), creating its folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))
    return path


_LOADERS: dict[str, Any] = {
    "sindy": "sdrl_bench.models.sindy:SindyModel",
    "nn": "sdrl_bench.models.nn:MLPDynamics",
    "pe": "sdrl_bench.models.pe:GaussianEnsembleDynamics",
}


def register_loader(kind: str, loader: str | type) -> None:
    """Make ``load_model`` read files of ``kind`` with ``loader``: a class with a classmethod
    ``from_saved(data: dict, path: Path)``, or its ``"module:Class"`` name (imported on first use)."""
    _LOADERS[kind] = loader


def _loader(kind: str) -> Any:
    loader = _LOADERS[kind]
    if isinstance(loader, str):
        module, _, attr = loader.partition(":")
        loader = _LOADERS[kind] = getattr(importlib.import_module(module), attr)
    return loader


def load_model(path: str | Path) -> DynamicsModel:
    """Load a saved model (``model.json``) of any registered kind; errors name the file."""
    data = read_model_json(path)
    kind = data.get("kind")
    if not isinstance(kind, str) or kind not in _LOADERS:
        raise ConfigError(f"{path}: model kind {kind!r} is not supported ({', '.join(_LOADERS)})")
    return _loader(kind).from_saved(data, Path(path))


def residual_noise(resid: np.ndarray, controls: np.ndarray, control_names: Sequence[str],
                   noise_by: Sequence[str]) -> dict[str, list]:
    """A model's step noise as its fit measured it: {control name: covariance of the residuals
    (N, n_states) on the rows where that one-hot control is 1} for each name of ``noise_by``
    (e.g. LunarLander's engines: their impulses carry random dispersion). Too few rows: left out."""
    resid, controls = np.asarray(resid, dtype=float), np.asarray(controls, dtype=float)
    out: dict[str, list] = {}
    for c in noise_by:
        rows = controls[:, list(control_names).index(c)] == 1.0
        if rows.sum() > resid.shape[1] + 1:
            out[c] = np.cov(resid[rows].T).tolist()
    return out
