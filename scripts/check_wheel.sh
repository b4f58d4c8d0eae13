#!/usr/bin/env bash
# The package as a user installs it: build the wheel, install it into a fresh venv outside the
# checkout (CPU torch first), and from an unrelated folder run every entry point (and task=dyna) on a tiny budget,
# with a user config dir (--config-dir) that adds a library the package does not ship.
#   bash scripts/check_wheel.sh            (CI runs it; about 3 minutes with a warm pip cache)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
PY=${PYTHON:-python3}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
echo "check_wheel: building the wheel"
rm -rf "$ROOT/build"  # a stale build/lib would carry deleted modules into the wheel
"$PY" -m pip wheel --quiet --no-deps --no-build-isolation -w "$WORK/dist" "$ROOT" 2>/dev/null \
  || "$PY" -m pip wheel --quiet --no-deps -w "$WORK/dist" "$ROOT"
WHEEL=$(ls "$WORK"/dist/sdrl_bench-*.whl)
# listed to a file first: `unzip -l | grep -q` under pipefail fails when grep exits before unzip
# has written the rest (SIGPIPE), which a clean-clone CI run hit once
unzip -l "$WHEEL" > "$WORK/wheel-files.txt"
grep -q "sdrl_bench/conf/config.yaml" "$WORK/wheel-files.txt" || { echo "check_wheel: the wheel holds no configs" >&2; exit 1; }
echo "check_wheel: installing $(basename "$WHEEL") into a fresh venv"
"$PY" -m venv "$WORK/venv"
V="$WORK/venv/bin"
"$V/python" -m pip install --quiet --upgrade pip
"$V/python" -m pip install --quiet "torch==2.13.0"
"$V/python" -m pip install --quiet "$WHEEL"
mkdir -p "$WORK/user/myconf/library"
cd "$WORK/user"
cat > myconf/library/user_cubic.yaml <<'YAML'
# A library of the user's own: cubic polynomials plus cos/sin of the states.
name: user_cubic
parts:
  - library: {_target_: pysindy.PolynomialLibrary, degree: 3, include_bias: true}
    inputs: all
  - library: {_target_: sdrl_bench.models.libraries.TrigLibrary, frequencies: [3.0]}
    inputs: [x]
YAML
run() { echo "check_wheel: $*"; "$@" > "$WORK/out.log" 2>&1 || { cat "$WORK/out.log"; echo "check_wheel: FAILED: $*" >&2; exit 1; }; tail -n 3 "$WORK/out.log"; }
run "$V/sdrl-bench"
run "$V/sdrl-bench" --config-dir myconf library=user_cubic
run "$V/sdrl-bench" task=train rl.surrogate_steps=64 rl.real_steps=64 rl.eval_every=64 rl.eval_episodes=1 \
    rl.final_episodes=1 agent.algo.train_freq=16 agent.algo.gradient_steps=2 agent.algo.batch_size=32 progress_bar=false
run "$V/sdrl-bench-search" search.n_trials=3
run "$V/sdrl-bench" experiment=dyna_mountain_car agent.n_envs=4 agent.algo.n_steps=16 agent.algo.batch_size=32 \
    agent.algo.n_epochs=1 rl.dyna.first_round_steps=64 rl.dyna.surrogate_steps_per_round=64 rl.dyna.max_rounds=1 \
    rl.dyna.eval_episodes=1 rl.dyna.final_episodes=1 rl.dyna.audit_episodes=1 progress_bar=false
run "$V/sdrl-bench-report" --name wheel
"$V/python" - <<'PY'
import sys
from mlflow.tracking import MlflowClient
client = MlflowClient("sqlite:///mlruns/mlflow.db")
exp = client.get_experiment_by_name("sdrl-bench")
runs = client.search_runs([exp.experiment_id])
kinds = sorted(r.data.tags.get("sdrl.kind", "?") for r in runs)
user = [r for r in runs if r.data.tags.get("library") == "user_cubic"]
bad = [r.info.run_id for r in runs if r.info.status != "FINISHED"]
print(f"check_wheel: runs {kinds}; user library runs {len(user)}; not FINISHED {bad}")
ok = (len(user) == 1 and "transfer" in kinds and "report" in kinds and kinds.count("fit") >= 2 and not bad
      and kinds.count("dyna") == 1 and kinds.count("dyna_round") == 2)
if ok:  # the user's library was used: its cos(3x) term is in the recovered law
    eq = open(client.download_artifacts(user[0].info.run_id, "model/equations.txt", ".")).read()
    print(eq)
    ok = "cos(3 x)" in eq
sys.exit(0 if ok else 1)
PY
test -f reports/wheel/report.md
# A user's own env (README "Add your own environment"): a gymnasium env registered in the user's
# package (tests/user_env.py writes it), its YAML in a --config-dir, fitted and transferred.
PYTHONPATH="$ROOT/tests" "$V/python" -c "from pathlib import Path; from user_env import write_user_dir; write_user_dir(Path('byo'))"
PYTHONPATH="$WORK/user/byo/src" run "$V/sdrl-bench" --config-dir byo/conf env=oscillator collector=random task=train agent=sac \
    rl.surrogate_steps=64 rl.real_steps=64 rl.eval_every=64 rl.eval_episodes=1 rl.final_episodes=1 \
    agent.algo.train_freq=16 agent.algo.gradient_steps=2 agent.algo.batch_size=32 progress_bar=false \
    tracking.uri=sqlite:///byo.db
grep -q "x\[k+1\] = 1 x +0.1 v" "$WORK/out.log" || { cat "$WORK/out.log"; echo "check_wheel: user env law not recovered" >&2; exit 1; }
echo "check_wheel: OK (installed wheel, entry points, --config-dir library and user env, report)"
