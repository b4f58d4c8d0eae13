#!/usr/bin/env bash
# Logged models used where the harness is not installed: fit three SINDy models with the
# harness (MountainCar's law; Pendulum's per-equation law, whose angle reads the clipped next
# velocity; a user's env from a config dir) and two NN models (an MLP and a probabilistic
# ensemble), then, in a fresh venv holding only mlflow and numpy, load each SINDy model by its
# models:/ URI from the store and check its predictions against the harness's own (<= 1e-12),
# and that sdrl_bench cannot be imported there; then add torch (the pinned CPU build) and do the
# same for the NN models.
#   bash scripts/check_model_venv.sh        (CI runs it; about 3 minutes with a warm pip cache)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
PY=${PYTHON:-python3}
HARNESS="$ROOT/.venv/bin/python"
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
cd "$WORK"
echo "check_model_venv: fitting with the harness"
PYTHONPATH="$ROOT/tests" "$HARNESS" - "$WORK" <<'PY'
import json, sys
from pathlib import Path
import numpy as np
from mlflow.tracking import MlflowClient
from sdrl_bench.cli.build import compose
from sdrl_bench.cli.main import run_fit
from user_env import write_user_dir

work = Path(sys.argv[1])
uri = f"sqlite:///{work / 'mlruns' / 'mlflow.db'}"
src, conf = write_user_dir(work / "user")
sys.path.insert(0, str(src))
cases = {}
for name, overrides in {"mountain_car": [], "pendulum": ["env=pendulum", "collector=random"],
                        "oscillator": [f"hydra.searchpath=[file://{conf}]", "env=oscillator", "collector=random"],
                        "nn": ["surrogate=nn", "surrogate.model.max_steps=300"],
                        "pe": ["env=pendulum", "collector=random", "surrogate=pe", "surrogate.model.max_steps=300"]}.items():
    result = run_fit(compose([f"tracking.uri={uri}", *overrides]))
    spec = result.job.spec
    x, u = spec.model_inputs(result.test.states, result.test.actions)
    run_id = MlflowClient(uri).search_runs(["1"], order_by=["attributes.start_time DESC"], max_results=1)[0].info.run_id
    (out,) = MlflowClient(uri).get_run(run_id).outputs.model_outputs
    cases[name] = {"uri": f"models:/{out.model_id}", "inputs": list(spec.input_names),
                   "z": np.concatenate([x, u], axis=1).tolist(), "expected": result.model.predict(x, u).tolist()}
(work / "cases.json").write_text(json.dumps({"tracking_uri": uri, "cases": cases}))
PY
echo "check_model_venv: a fresh venv with mlflow and numpy only"
"$PY" -m venv "$WORK/venv"
V="$WORK/venv/bin"
MLFLOW_VERSION=$("$HARNESS" -c 'import mlflow; print(mlflow.__version__)')
{ "$V/python" -m pip install --quiet --upgrade pip && "$V/python" -m pip install --quiet "mlflow==$MLFLOW_VERSION" numpy; } \
  > "$WORK/pip.log" 2>&1 || { cat "$WORK/pip.log"; echo "check_model_venv: installing mlflow failed" >&2; exit 1; }
CHECK=$(cat <<'PY'
import importlib.util, json, sys
from pathlib import Path
import mlflow, numpy as np, pandas as pd

assert importlib.util.find_spec("sdrl_bench") is None, "sdrl_bench must not be importable here"
data = json.loads((Path(sys.argv[1]) / "cases.json").read_text())
mlflow.set_tracking_uri(data["tracking_uri"])
names = sys.argv[2].split(",")
if sys.argv[3] == "no-torch":
    assert importlib.util.find_spec("torch") is None, "torch must not be importable here"
for name, case in ((n, data["cases"][n]) for n in names):
    model = mlflow.pyfunc.load_model(case["uri"])
    pred = model.predict(pd.DataFrame(case["z"], columns=case["inputs"])).to_numpy()
    err = float(np.max(np.abs(pred - np.asarray(case["expected"]))))
    assert err <= 1e-12, (name, err)
    print(f"check_model_venv: {name}: {case['uri']} loaded without the harness ({sys.argv[3]}); "
          f"{len(pred)} predictions, max |diff| {err:.1e}")
PY
)
"$V/python" -c "$CHECK" "$WORK" mountain_car,pendulum,oscillator no-torch
echo "check_model_venv: adding torch (the NN models' only other requirement)"
TORCH_VERSION=$("$HARNESS" -c 'import torch; print(torch.__version__.split("+")[0])')
"$V/python" -m pip install --quiet "torch==$TORCH_VERSION" > "$WORK/pip.log" 2>&1 \
  || { cat "$WORK/pip.log"; echo "check_model_venv: installing torch failed" >&2; exit 1; }
"$V/python" -c "$CHECK" "$WORK" nn,pe torch
echo "check_model_venv: OK"
