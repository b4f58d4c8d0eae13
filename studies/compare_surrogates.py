"""SINDy vs NN from a tracking store: per-state held-out MSE, fit time and parameter ratios.

Pairs every finished SINDy fit run with the NN fit run of the same env, dataset hash, test-set
hash and seed (``sdrl_bench.report.compare``) and prints both models' one-step MSE per state and the
SINDy / NN ratios. ``--log`` also records the ratios as metrics (``sindy_over_nn/*``) on each
pair's NN run, so they sit beside the run's own metrics in the MLflow UI.

    .venv/bin/sdrl-bench -m env=mountain_car,lunar_lander surrogate=sindy,nn \\
        tracking.uri=sqlite:///runs/nn_cmp/mlflow.db
    .venv/bin/python studies/compare_surrogates.py --uri sqlite:///runs/nn_cmp/mlflow.db --log
"""

from __future__ import annotations

import argparse

from tabulate import tabulate

from sdrl_bench import tracking
from sdrl_bench.report.compare import PREFIX, comparison_rows, surrogate_ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uri", default=None, help="tracking URI (default: as sdrl-bench resolves it)")
    parser.add_argument("--experiment", default="sdrl-bench")
    parser.add_argument("--log", action="store_true", help="log the ratios on each pair's NN run")
    args = parser.parse_args()
    from sdrl_bench.cli.args import store

    if args.uri:
        store(parser, args.uri)
    uri = tracking.resolve_uri(args.uri)
    runs = tracking.find_runs(uri, args.experiment, "tags.`sdrl.kind` = 'fit'", missing_ok=False)
    rows = comparison_rows(runs)
    if not rows:
        print(f"no (sindy, nn) fit pairs on identical data in {uri}")
        return
    by_id = {r["run_id"]: r for r in runs}
    for row in rows:
        states = [k[len("sindy mse/"):] for k in row if k.startswith("sindy mse/")]
        table = [[s, row[f"sindy mse/{s}"], row[f"nn mse/{s}"], row[f"{PREFIX}/mse/{s}"]] for s in states]
        print(f"\n{row['env']} (seed {row['seed']}, dataset {row['dataset_sha256'][:12]}): one-step MSE, raw units")
        print(tabulate(table, headers=["state", "SINDy", "NN", "SINDy/NN"], floatfmt=".3g"))
        print(f"fit wall: SINDy {row['sindy fit_wall_seconds']:.4f} s, NN {row['nn fit_wall_seconds']:.3f} s "
              f"(SINDy/NN {row[f'{PREFIX}/fit_wall_seconds']:.2g}, NN {row['nn_over_sindy/fit_wall_seconds']:.0f}x "
              f"slower); CPU SINDy/NN {row[f'{PREFIX}/fit_cpu_seconds']:.2g}; parameters: SINDy "
              f"{row['sindy n_parameters']:.0f} active terms, NN {row['nn n_parameters']:.0f} weights "
              f"(SINDy/NN {row[f'{PREFIX}/n_parameters']:.2g})")
        if args.log:
            ratios = surrogate_ratios(by_id[row["sindy_run"]]["metrics"], by_id[row["nn_run"]]["metrics"])
            tracking.Run(uri, row["nn_run"]).log_metrics(ratios)
            print(f"logged {len(ratios)} ratios on NN run {row['nn_run']}")


if __name__ == "__main__":
    main()
