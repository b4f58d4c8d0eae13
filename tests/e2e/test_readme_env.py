"""The README's own-environment example, as a user copies it: its ``my_envs/task.py`` and
``myconf/env/my_env.yaml`` blocks taken from README.md itself, beside a registered env of the
README's shape (a body above a floor: height h >= 0, velocity v, one thrust), and its command
run with tiny budgets. A key the example leaves out (the library's degree, the optimizer's
defaults) or a field it misnames fails here, not on a user's machine."""

from __future__ import annotations

import os
import re
from pathlib import Path

from helpers import run_cli, search
from user_env import FALLER_MODULE

README = Path(__file__).resolve().parents[2] / "README.md"
TINY = ("rl.surrogate_steps=200", "rl.real_steps=64", "rl.eval_every=200", "rl.eval_episodes=1", "rl.final_episodes=2",
        "agent=sac", "agent.algo.train_freq=16", "agent.algo.gradient_steps=1", "agent.algo.batch_size=32",
        "agent.algo.learning_starts=32", "agent.algo.policy_kwargs.net_arch=[16]", "progress_bar=false")


def _block(first_line: str) -> str:
    """The README's fenced code block whose first line is ``first_line``."""
    found = re.findall(r"```[a-z]*\n(" + re.escape(first_line) + r"\n.*?)```", README.read_text(), flags=re.S)
    assert len(found) == 1, f"README.md: no single code block starting {first_line!r}"
    return found[0]


def test_the_readmes_own_env_example_runs_as_written(tmp_path, store):
    pkg = tmp_path / "my_envs"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(FALLER_MODULE.replace('gym.register("Faller-v0", entry_point="faller_envs:Faller"',
                                                           'gym.register("MyEnv-v0", entry_point="my_envs:Faller"'))
    (pkg / "task.py").write_text(_block("# my_envs/task.py: states (N, n_state) in state_names order, raw actions (N, width)"))
    conf = tmp_path / "myconf" / "env"
    conf.mkdir(parents=True)
    (conf / "my_env.yaml").write_text(_block("# myconf/env/my_env.yaml"))
    command = _block("PYTHONPATH=$PWD sdrl-bench --config-dir myconf env=my_env collector=random task=train").split()
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(tmp_path), os.environ.get("PYTHONPATH", "")) if p)}
    res = run_cli(*command[2:], *TINY, f"tracking.uri={store}", cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    runs = search(store)
    assert list(runs["status"]) == ["FINISHED"]
    row = runs.iloc[0]
    assert row["tags.env"] == "my_env"
    assert row["metrics.surrogate/real_steps/model_data"] == 600  # the YAML's n_transitions, all counted
    # the README's event, learned from the run's own impacts (random thrust: both outcomes occur)
    assert row["metrics.events/impact/n_events"] >= 8 and row["metrics.events/impact/learned"] == 1.0
