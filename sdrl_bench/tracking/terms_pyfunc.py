"""A SINDy model as a self-contained MLflow pyfunc: numpy and MLflow, nothing of the harness.

MLflow copies this file into the logged model (models-from-code) and runs it on
``mlflow.pyfunc.load_model``; the model itself is data, ``terms.json``: the model's input and
output names, its terms (products of factors ``[input index, op, parameter]``), its
coefficient matrix, and, for a per-equation model whose primed terms read a bounded next
value, the stages in which to evaluate it. ``predict`` is the dynamics model's next-state
prediction: a DataFrame with one column per model input (regressed states, then controls:
exogenous states and encoded actions, by name) gives one column per regressed state's next
value. It is not the surrogate's whole step (no env bounds, no task).

Why a second evaluator, hand-written: a logged model must load where the harness is not
installed, so this file may import nothing from it. The ops below are those of
``sdrl_bench.models.terms.TABLE`` (pow, sin, cos, rat, xrat), written again in numpy; the
harness's tests check that this evaluator and the harness's own agree to 1e-12.
"""

import json
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
from mlflow.pyfunc import PythonModel

OPS = {
    "pow": lambda p, x: x,
    "sin": lambda p, x: np.sin(x if p == 1.0 else p * x),
    "cos": lambda p, x: np.cos(x if p == 1.0 else p * x),
    "rat": lambda p, x: 1.0 / (1.0 + x * x),
    "xrat": lambda p, x: x / (1.0 + x * x),
}


def features(terms, z):
    """(N, n_terms) values of the terms at inputs z (N, n_inputs)."""
    out = np.ones((z.shape[0], len(terms)))
    for k, term in enumerate(terms):
        for j, op, p in term:
            out[:, k] *= OPS[op](p, z[:, j])
    return out


def predict_next(table, z):
    """Next regressed states (N, n_outputs) of the model ``table`` (terms.json) at inputs z."""
    coef = np.asarray(table["coef"], dtype=float)
    terms = table["terms"]
    stages = table.get("stages")
    if not stages:
        return features(terms, z) @ coef.T
    extra = sum(len(st["clips"]) for st in stages["stages"])
    ext = np.concatenate([z, np.zeros((z.shape[0], extra))], axis=1)
    out = np.empty((z.shape[0], coef.shape[0]))
    for st in stages["stages"]:
        rows = st["rows"]
        out[:, rows] = features(terms, ext) @ coef[rows].T
        for row, col, lo, hi in st["clips"]:
            ext[:, col] = np.clip(out[:, row], lo, hi)
    return out


class TermsPyfunc(PythonModel):
    def load_context(self, context) -> None:
        self.table = json.loads(Path(context.artifacts["terms"]).read_text())

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        df = pd.DataFrame(model_input)
        z = df[self.table["inputs"]].to_numpy(dtype=float)
        with np.errstate(all="ignore"):
            nxt = predict_next(self.table, z)
        return pd.DataFrame(nxt, columns=[f"{s}_next" for s in self.table["outputs"]], index=df.index)


mlflow.models.set_model(TermsPyfunc())
