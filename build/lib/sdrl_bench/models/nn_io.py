"""Saving and loading ``MLPDynamics`` as data: JSON metadata plus a tensor-only state dict.

``model.json`` holds the format tag, the kind, the hyperparameters, the state and control
names, the normalization statistics, the training outcome, and the name and sha256 of the
weights file (``model.pt``, written by ``torch.save`` from a dict of tensors and read back with
``torch.load(weights_only=True)``: loading never runs code from the artifact). A weights file
whose keys, shapes, dtype or hash do not match the metadata raises ``ConfigError`` naming it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from sdrl_bench import ConfigError
from sdrl_bench.models.base import read_model_json

if TYPE_CHECKING:
    from sdrl_bench.models.nn import MLPDynamics

FORMAT = "sdrl-bench/nn-model-v1"
TRAINING_KEYS = ("epochs_run", "steps_run", "n_train_rows", "n_val_rows", "val_member_std", "n_fit_samples")


def param_names(n_layers: int) -> list[str]:
    """State-dict keys in parameter order: layers.<i>.weight, layers.<i>.bias."""
    return [f"layers.{i}.{w}" for i in range(n_layers) for w in ("weight", "bias")]


def expected_shapes(model: MLPDynamics, n_in: int, n_out: int) -> dict[str, tuple[int, ...]]:
    sizes = model.layer_sizes(n_in, n_out)
    k, shapes = model.ensemble_size, {}
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        shapes[f"layers.{i}.weight"], shapes[f"layers.{i}.bias"] = (k, a, b), (k, b)
    return shapes


def to_dict(model: MLPDynamics, weights_file: str, sha256: str) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "kind": model.kind,
        "hyperparameters": model.hyperparameters(),
        "state_names": model.state_names_,
        "control_names": model.control_names_,
        "input_mean": model.input_mean_.tolist(),
        "input_std": model.input_std_.tolist(),
        "output_mean": model.output_mean_.tolist(),
        "output_std": model.output_std_.tolist(),
        "training": {
            **{k: getattr(model, f"{k}_") for k in TRAINING_KEYS},
            "best_val_loss": model.best_val_loss_.tolist(),
            "best_epoch": model.best_epoch_.tolist(),
        },
        "n_parameters": model.n_parameters,
        "weights_file": weights_file,
        "weights_sha256": sha256,
    }


def save(model: MLPDynamics, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    weights = path.with_suffix(".pt")
    names = param_names(len(model.params_) // 2)
    torch.save({n: p.detach().clone().contiguous() for n, p in zip(names, model.params_, strict=True)}, weights)
    sha = hashlib.sha256(weights.read_bytes()).hexdigest()
    path.write_text(json.dumps(to_dict(model, weights.name, sha), indent=1))
    return path


def _vector(d: dict, key: str, n: int, positive: bool = False) -> np.ndarray:
    v = np.asarray(d[key], dtype=float)
    if v.shape != (n,) or not np.all(np.isfinite(v)) or (positive and not np.all(v > 0)):
        raise ValueError(f"'{key}' must be {n} finite{' positive' if positive else ''} numbers")
    return v


def load(cls: type[MLPDynamics], path: Path) -> MLPDynamics:
    d = read_model_json(path)
    try:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ValueError(f"format is {d.get('format') if isinstance(d, dict) else None!r}, expected {FORMAT!r}")
        model = cls(**d["hyperparameters"])
        model.state_names_ = [str(s) for s in d["state_names"]]
        model.control_names_ = [str(s) for s in d["control_names"]]
        n_in, n_out = len(model.state_names_) + len(model.control_names_), len(model.state_names_)
        model.input_mean_, model.input_std_ = _vector(d, "input_mean", n_in), _vector(d, "input_std", n_in, True)
        model.output_mean_ = _vector(d, "output_mean", n_out)
        model.output_std_ = _vector(d, "output_std", n_out, True)
        t = d["training"]
        for k in TRAINING_KEYS:
            setattr(model, f"{k}_", t[k])
        model.best_val_loss_ = np.asarray(t["best_val_loss"], dtype=float)
        model.best_epoch_ = np.asarray(t["best_epoch"], dtype=int)
        weights_file, sha = str(d["weights_file"]), str(d["weights_sha256"])
        if Path(weights_file).name != weights_file:
            raise ValueError(f"weights_file must be a file name beside the metadata, got {weights_file!r}")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: not a valid NN model file ({exc})") from exc
    weights = path.parent / weights_file
    model.params_ = _read_state_dict(weights, path, expected_shapes(model, n_in, n_out), model.dtype, sha)
    from sdrl_bench.models.nn import ACTIVATIONS

    model._act = ACTIVATIONS[model.activation]
    return model


def _read_state_dict(weights: Path, meta: Path, shapes: dict[str, tuple[int, ...]], dtype: str,
                     sha: str) -> list[torch.Tensor]:
    def mismatch(what: str) -> ConfigError:
        return ConfigError(f"{weights}: state dict does not match its metadata {meta.name} ({what})")

    if not weights.is_file():
        raise ConfigError(f"{weights}: weights file named by {meta} not found")
    try:
        state = torch.load(weights, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for unreadable or unsafe files
        raise ConfigError(f"{weights}: not a readable tensor state dict ({exc.__class__.__name__})") from None
    if not isinstance(state, dict):
        raise mismatch(f"holds a {type(state).__name__}, not a dict of tensors")
    if set(state) != set(shapes):
        missing, extra = sorted(set(shapes) - set(state)), sorted(set(state) - set(shapes))
        raise mismatch(f"missing keys {missing}, unexpected keys {extra}")
    params = []
    for name, shape in shapes.items():
        t = state[name]
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
            got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise mismatch(f"{name} has shape {got}, expected {shape}")
        if str(t.dtype) != f"torch.{dtype}":
            raise mismatch(f"{name} is {t.dtype}, expected {dtype}")
        if not bool(torch.all(torch.isfinite(t))):
            raise mismatch(f"{name} has non-finite values")
        params.append(t.contiguous())
    if hashlib.sha256(weights.read_bytes()).hexdigest() != sha:
        raise mismatch("sha256 differs from weights_sha256")
    return params
