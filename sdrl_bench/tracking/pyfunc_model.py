"""The surrogate as an MLflow pyfunc, logged from code (MLflow's models-from-code): MLflow
copies this file into the logged model and runs it on ``mlflow.pyfunc.load_model``; the
model itself stays data (``model.json``, and an NN's state dict), loaded by the project's own
``load_model``, never a pickle.

Input: a DataFrame with the dataset CSV's state and action columns (``s_<state>``,
``a_<i>``); output: the next regressed states (``ns_<state>``), bounds applied as the real env
applies them: the one-step prediction ``sdrl_bench.fidelity.step`` makes. Needs sdrl_bench
installed where the model is loaded.
"""

import json

import mlflow
import pandas as pd
from mlflow.pyfunc import PythonModel


class SurrogatePyfunc(PythonModel):
    def load_context(self, context) -> None:
        from pathlib import Path

        from sdrl_bench.envs.base import find_spec
        from sdrl_bench.models.base import load_model

        self.model = load_model(Path(context.artifacts["model"]) / "model.json")
        self.spec = find_spec(json.loads(Path(context.artifacts["env"]).read_text())["env"])

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        import numpy as np

        from sdrl_bench.fidelity import step

        spec = self.spec
        df = pd.DataFrame(model_input)
        states = df[[f"s_{n}" for n in spec.state_names]].to_numpy(dtype=float)
        actions = df[[f"a_{i}" for i in range(spec.raw_action_width)]].to_numpy(dtype=float)
        with np.errstate(all="ignore"):
            nxt = step(self.model, spec, states, actions)
        return pd.DataFrame(nxt, columns=[f"ns_{n}" for n in spec.target_names], index=df.index)


mlflow.models.set_model(SurrogatePyfunc())
