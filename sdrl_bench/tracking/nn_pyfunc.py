"""An NN dynamics model (``surrogate=nn`` or ``surrogate=pe``) as a self-contained MLflow pyfunc:
MLflow, numpy and torch, nothing of the harness.

MLflow copies this file into the logged model (models-from-code) and runs it on
``mlflow.pyfunc.load_model``; the model itself is data, the harness's own NN files: ``model.json``
(format ``sdrl-bench/nn-model-v1``: names, normalization statistics, layer sizes, activation,
dtype, the elites of a probabilistic ensemble) and ``model.pt`` (the network's state dict: a
plain dict of tensors, read with ``torch.load(weights_only=True)``, so loading runs no code from
the artifact; its sha256 is checked against the metadata). ``predict`` is the dynamics model's
next-state prediction, the harness's ``predict``: the mean over the members (a probabilistic
ensemble: over its elites, of each elite's Gaussian mean). A DataFrame with one column per model
input (regressed states, then controls, by name) gives one column per regressed state's next
value. It is not the surrogate's whole step (no noise, no env bounds, no task).

Why a second forward pass, hand-written: a logged model must load where the harness is not
installed, so this file may import nothing from it. The network is the stack of the harness's
``models.mlp.EnsembleLinear`` layers (``h @ weight[k] + bias[k]``, an activation between layers)
with, for a probabilistic ensemble, mean and log-variance halves of the last layer (only the
means are used here); the same torch operations in the same order, so the predictions equal the
harness's (the harness's tests check it to 1e-12).
"""

import hashlib
import json
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from mlflow.pyfunc import PythonModel

ACTIVATIONS = {"tanh": torch.tanh, "relu": F.relu, "silu": F.silu, "elu": F.elu, "gelu": F.gelu}
DTYPES = {"float32": (torch.float32, np.float32), "float64": (torch.float64, np.float64)}


def load_network(model_dir):
    """(metadata, layers [(weight, bias)], activation, torch dtype, numpy dtype) of ``model.json``."""
    meta = json.loads((Path(model_dir) / "model.json").read_text())
    if meta.get("format") != "sdrl-bench/nn-model-v1":
        raise ValueError(f"{model_dir}/model.json: not an sdrl-bench NN model ({meta.get('format')!r})")
    weights = Path(model_dir) / meta["weights_file"]
    if hashlib.sha256(weights.read_bytes()).hexdigest() != meta["weights_sha256"]:
        raise ValueError(f"{weights}: sha256 differs from its metadata")
    state = torch.load(weights, map_location="cpu", weights_only=True)
    prefix = "body.layers." if meta["kind"] == "pe" else "layers."
    n_layers = sum(1 for k in state if k.startswith(prefix) and k.endswith(".weight"))
    layers = [(state[f"{prefix}{i}.weight"], state[f"{prefix}{i}.bias"]) for i in range(n_layers)]
    hp = meta["hyperparameters"]
    t_dtype, np_dtype = DTYPES[hp.get("dtype", "float32")]
    return meta, layers, ACTIVATIONS[hp["activation"]], t_dtype, np_dtype


def forward(layers, act, zn):
    """(K, N, out) outputs of the K members at normalized inputs zn (N, in)."""
    h = zn
    for i, (w, b) in enumerate(layers):
        h = torch.addmm(b[0], h, w[0]) if h.dim() == 2 and w.shape[0] == 1 else torch.matmul(h, w) + b.unsqueeze(1)
        if i < len(layers) - 1:
            h = act(h)
    return h if h.dim() == 3 else h.unsqueeze(0)


def predict_next(loaded, x, u):
    """Next regressed states (N, n_states), float64, from states x and controls u."""
    meta, layers, act, _, np_dtype = loaded
    mean_in, std_in = np.asarray(meta["input_mean"]), np.asarray(meta["input_std"])
    mean_out, std_out = np.asarray(meta["output_mean"]), np.asarray(meta["output_std"])
    zn = (np.concatenate([x, u], axis=1) - mean_in) / std_in
    with torch.inference_mode():
        out = forward(layers, act, torch.from_numpy(zn.astype(np_dtype, copy=False))).numpy()
    n = x.shape[1]
    if meta["kind"] == "pe":  # each elite's Gaussian mean, then their mean
        members = x + out[meta["elites"]].astype(float)[..., :n] * std_out + mean_out
        return members.mean(axis=0)
    mean = out[0].astype(float) if len(out) == 1 else out.mean(axis=0, dtype=np.float64)
    return x + (mean * std_out + mean_out)


class NNDynamicsPyfunc(PythonModel):
    def load_context(self, context) -> None:
        self.loaded = load_network(context.artifacts["model"])

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        meta = self.loaded[0]
        df = pd.DataFrame(model_input)
        x = df[list(meta["state_names"])].to_numpy(dtype=float)
        u = df[list(meta["control_names"])].to_numpy(dtype=float)
        with np.errstate(all="ignore"):
            nxt = predict_next(self.loaded, x, u)
        return pd.DataFrame(nxt, columns=[f"{s}_next" for s in meta["state_names"]], index=df.index)


mlflow.models.set_model(NNDynamicsPyfunc())
