"""The protocol every dynamics model follows, and loading a saved model by its kind."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Protocol, runtime_checkable
from collections.abc import Sequence

import numpy as np

from sdrl_bench import ConfigError


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
            state_names: Sequence[str], control_names: Sequence[str]) -> DynamicsModel: ...

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


def load_model(path: str | Path) -> DynamicsModel:
    """Load a saved model (``model.json``) of any kind; errors name the file."""
    data = read_model_json(path)
    kind = data.get("kind")
    if kind == "sindy":
        from sdrl_bench.models.sindy import SindyModel

        return SindyModel.from_dict(data, source=str(path))
    if kind == "nn":
        from sdrl_bench.models.nn import MLPDynamics  # torch only when needed

        return MLPDynamics.load(path)
    raise ConfigError(f"{path}: model kind {kind!r} is not supported (sindy, nn)")
