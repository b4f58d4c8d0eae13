"""Recording a Dyna run: one child run per round under the Dyna run (the parent).

Each child holds that round's refit as a fit run holds it (metrics, model, equations, figures;
its data file holds the rows the round added, so the rounds' files together are the model
data, each row stored once), the learned event models, the agent's real
returns and the running account of real steps. The parent holds the learning curve against
real transitions (``dyna/curve_return_mean`` at step = real transitions so far), the summary,
the final agent, the audit, and a figure of the curve beside the real arm's when the store has
a finished real arm of the same key.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from sdrl_bench.tracking.client import Run, mlflow_client, start_run


class DynaRunRecorder:
    """``rl.dyna.DynaRecorder`` into MLflow: a child run per round under ``parent``."""

    def __init__(self, parent: Run, experiment: str, run_name: str, tags: dict[str, Any]):
        self.parent, self.experiment, self.run_name, self.tags = parent, experiment, run_name, tags
        self.child_ids: list[str] = []

    def round_done(self, result, agent) -> None:
        from sdrl_bench.tracking.fit import log_fit

        tags = {**self.tags, "sdrl.kind": "dyna_round", "dyna.round": result.round}
        with start_run(self.parent.uri, self.experiment, f"{self.run_name}-round{result.round}", tags,
                       self.parent.run_id) as child:
            if result.refit:
                log_fit(child, result.fit, model=False, rows=result.new_data)
            elif len(result.new_data):  # the last round's real rows, recorded but never fitted
                with tempfile.TemporaryDirectory() as tmp:
                    from sdrl_bench.data import save_csv

                    spec = result.fit.job.spec
                    child.log_artifact(save_csv(result.new_data, spec, Path(tmp) / f"{spec.name}_unfitted_rows.csv"), "data")
            child.log_metrics(result.metrics())
            for name, res in (("screen", result.screen), ("final", result.final)):
                if res is not None:
                    import pandas as pd

                    child.log_text(pd.DataFrame({"return": res.returns, "length": res.lengths, "success": res.successes})
                                   .to_csv(index=False), f"eval/{name}.csv")
        self.child_ids.append(child.run_id)
        m = result.metrics()
        self.parent.log_metrics({k: m[k] for k in ("real_transitions_total", "real_transitions_model", "surrogate_steps")},
                                step=result.round)
        if result.screen is not None:
            self.parent.log_metrics({"dyna/curve_return_mean": result.screen.mean,
                                     "dyna/curve_return_std": result.screen.std}, step=result.screened_at)

    def sb3_logger(self):
        """SB3's training metrics into the parent run (``dyna/sb3/...``, step = surrogate steps so far)."""
        from sdrl_bench.tracking.sb3 import sb3_logger

        return sb3_logger(self.parent, "dyna/sb3")

    def real_arm_curve(self, key: str) -> tuple[list[int], list[float], list[float]] | None:
        """The curve of a finished real arm with ``key`` in the store (training steps, means, stds)."""
        import pandas as pd

        from sdrl_bench.tracking.transfer import find_real_arm

        found = find_real_arm(self.parent.uri, self.experiment, key)
        if found is None:
            return None
        with tempfile.TemporaryDirectory() as tmp:
            path = mlflow_client(self.parent.uri).download_artifacts(found["run_id"], "curves/real.csv", tmp)
            curve = pd.read_csv(path)
        self.parent.set_tags({"dyna.real_arm_run": found["run_id"]})
        return curve["train_steps"].tolist(), curve["return_mean"].tolist(), curve["return_std"].tolist()

    def finish(self, outcome, spec, real_key: str | None, title: str) -> None:
        """The summary, the final agent, the learning curve (CSV and figure)."""
        import pandas as pd

        from sdrl_bench.plots import learning_curves

        self.parent.log_metrics(outcome.summary)
        if real_key:  # the real arm it is compared with, found later by this key if not run yet
            self.parent.set_tags({"dyna.real_arm_key": real_key})
        steps = [c[0] for c in outcome.curve]
        self.parent.log_text(pd.DataFrame({"real_transitions": steps, "return_mean": [c[1] for c in outcome.curve],
                                           "return_std": [c[2] for c in outcome.curve]}).to_csv(index=False),
                             "curves/dyna.csv")
        with tempfile.TemporaryDirectory() as tmp:  # the model data: the rounds' data files, together
            path = Path(tmp) / "dyna.zip"
            outcome.agent.save(path)
            self.parent.log_artifact(path, "agents")
        curves = {"Dyna (x: every real step of the loop)": (steps, [c[1] for c in outcome.curve], [c[2] for c in outcome.curve])}
        real = self.real_arm_curve(real_key) if real_key else None
        if real is not None:
            curves["real arm (x: its training steps; its evaluations not counted)"] = real
        fig = learning_curves(curves, spec.solved_threshold, title, x_label="real transitions")
        self.parent.log_figure(fig, "figures/learning_curve_real_transitions.png")
