"""Saving and loading ``MLPDynamics`` as data: JSON metadata plus a tensor-only state dict.

``model.json`` holds the format tag, the kind, the hyperparameters, the state and control
names, the normalization statistics, the training outcome, and the name and sha256 of the
weights file (``model.pt``: the network's state dict, written by ``torch.save`` and read back
with ``torch.load(weights_only=True)``: loading never runs code from the artifact).

Keys and shapes are checked by ``load_state_dict(strict=True)``; this module adds what torch
does not do: the metadata, the dtype and finiteness of the weights (``load_state_dict`` would
cast and copy them silently), the sha256, and one-line ``ConfigError``s naming the file.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sdrl_bench import ConfigError
from sdrl_bench.models.base import write_model_json

FORMAT = "sdrl-bench/nn-model-v1"
TRAINING_KEYS = ("epochs_run", "steps_run", "n_train_rows", "n_val_rows", "val_member_std", "n_fit_samples")


def to_dict(model: Any, weights_file: str, sha256: str) -> dict[str, Any]:
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
        "noise": model.noise_,
        **({"elites": [int(i) for i in model.elites_]} if hasattr(model, "elites_") else {}),
        "n_parameters": model.n_parameters,
        "weights_file": weights_file,
        "weights_sha256": sha256,
    }


def save(model: Any, path: Path) -> Path:
    """Write ``path`` (the metadata of an ``MLPDynamics``) and ``<stem>.pt`` beside it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    weights = path.with_suffix(".pt")
    torch.save(dict(model.net_.state_dict()), weights)  # a plain dict of tensors
    sha = hashlib.sha256(weights.read_bytes()).hexdigest()
    return write_model_json(path, to_dict(model, weights.name, sha))


def _vector(d: dict, key: str, n: int, positive: bool = False) -> np.ndarray:
    v = np.asarray(d[key], dtype=float)
    if v.shape != (n,) or not np.all(np.isfinite(v)) or (positive and not np.all(v > 0)):
        raise ValueError(f"'{key}' must be {n} finite{' positive' if positive else ''} numbers")
    return v


def load(cls: type, d: dict, path: Path) -> Any:
    """An ``MLPDynamics`` (``cls``) from its metadata ``d`` (read from ``path``) and weights file."""
    try:
        if d.get("format") != FORMAT:
            raise ValueError(f"format is {d.get('format')!r}, expected {FORMAT!r}")
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
        model.noise_ = {str(k): np.asarray(v, dtype=float).tolist() for k, v in d.get("noise", {}).items()}
        if "elites" in d:  # a probabilistic ensemble's (models.pe)
            model.elites_ = np.asarray(d["elites"], dtype=int)
            if not np.all((model.elites_ >= 0) & (model.elites_ < model.ensemble_size)):
                raise ValueError(f"'elites' must index the {model.ensemble_size} members, got {d['elites']}")
        weights_file, sha = str(d["weights_file"]), str(d["weights_sha256"])
        if Path(weights_file).name != weights_file:
            raise ValueError(f"weights_file must be a file name beside the metadata, got {weights_file!r}")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: not a valid NN model file ({exc})") from exc
    model.net_ = model.network(n_in, n_out)
    _load_weights(model.net_, path.parent / weights_file, path, sha)
    model.net_.requires_grad_(False)
    return model


def _load_weights(net: torch.nn.Module, weights: Path, meta: Path, sha: str) -> None:
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
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as exc:  # torch's message: a header line, then one line per problem
        problems = [line.strip() for line in str(exc).splitlines()[1:] if line.strip()]
        raise mismatch(re.sub(r"torch\.Size\(\[([^\]]*)\]\)", r"(\1)", "; ".join(problems))) from None
    dtype = next(net.parameters()).dtype
    for name, t in state.items():
        if t.dtype != dtype:
            raise mismatch(f"{name} is {t.dtype}, expected {dtype}")
        if not bool(torch.all(torch.isfinite(t))):
            raise mismatch(f"{name} has non-finite values")
    if hashlib.sha256(weights.read_bytes()).hexdigest() != sha:
        raise mismatch("sha256 differs from weights_sha256")
