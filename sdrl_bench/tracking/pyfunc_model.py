"""A dynamics model of any kind as an MLflow pyfunc, logged from code (MLflow's models-from-code):
MLflow copies this file into the logged model and runs it on ``mlflow.pyfunc.load_model``; the
model itself stays data (``model.json``, and an NN's state dict), loaded by the harness's own
``load_model``, never a pickle. Needs sdrl_bench installed where it is loaded (a SINDy model is
logged self-contained instead: ``terms_pyfunc.py``).

Input: a DataFrame with one column per model input (the regressed states, then the controls:
exogenous states and encoded actions, by name); output: the next regressed states
(``<state>_next``), the dynamics model's own prediction. No env is needed to load it.
"""

from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
from mlflow.pyfunc import PythonModel


class DynamicsPyfunc(PythonModel):
    def load_context(self, context) -> None:
        from sdrl_bench.models.base import load_model

        self.model = load_model(Path(context.artifacts["model"]) / "model.json")

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        m = self.model
        df = pd.DataFrame(model_input)
        x = df[list(m.state_names_)].to_numpy(dtype=float)
        u = df[list(m.control_names_)].to_numpy(dtype=float)
        with np.errstate(all="ignore"):
            nxt = np.asarray(m.predict(x, u), dtype=float)
        return pd.DataFrame(nxt, columns=[f"{s}_next" for s in m.state_names_], index=df.index)


mlflow.models.set_model(DynamicsPyfunc())
