"""The report's figures: learning curves pooled across seeds (drawn here), and the runs' own
figure artifacts (policy maps, predicted vs true, Optuna history and Pareto front) and
equations, fetched through ``tracking`` into the report folder."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any
from collections.abc import Callable, Mapping, Sequence

import pandas as pd

from sdrl_bench.report import tables as rt
from sdrl_bench import tracking
from sdrl_bench.report.render import Block, Equations, Heading, Image, Para

UrlFn = Callable[[str], "str | None"]


def _ref(run_id: str, url: UrlFn) -> str:
    u = url(run_id)
    return f"[{run_id[:8]}]({u})" if u else f"`{run_id}`"


def _fetch(uri: str, run_id: str, artifact: str, dest: Path) -> Path | None:
    """One run artifact copied to ``dest`` (a file path in the report folder); None if absent."""
    got = tracking.download_artifact(uri, run_id, artifact, dest.parent / f".dl-{run_id}")
    if got is None or not got.is_file():
        return None
    dest.parent.mkdir(parents=True, exist_ok=True)
    got.replace(dest)
    return dest


def _curves(uri: str, runs: Sequence[Mapping[str, Any]], arm: str, tmp: Path) -> list[pd.DataFrame]:
    out = []
    for r in runs:
        path = tracking.download_artifact(uri, r["run_id"], f"curves/{arm}.csv", tmp / r["run_id"])
        if path is not None and path.is_file():
            out.append(pd.read_csv(path))
    return out


def learning_curve_figure(bands: Mapping[str, pd.DataFrame], title: str, solved: float | None) -> bytes:
    """Real return vs training steps per arm: the mean across seeds, shaded min..max."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.subplots()
    for arm, band in bands.items():
        if len(band):
            line, = ax.plot(band["train_steps"], band["mean"], label=f"{arm} (n={int(band['n'].max())} seeds)")
            ax.fill_between(band["train_steps"], band["low"], band["high"], alpha=0.25, color=line.get_color())
    if solved is not None:
        ax.axhline(solved, ls="--", color="gray", lw=1, label=f"solved ({solved:g})")
    ax.set_xlabel("training steps (in the arm's environment)")
    ax.set_ylabel("real return")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def _solved_threshold(runs: Sequence[Mapping[str, Any]]) -> float | None:
    """The env's solved threshold as its transfer runs recorded it (tag ``solved_threshold``)."""
    values = {r["tags"].get("solved_threshold") for r in runs} - {None, "", "None"}
    return float(min(values, key=float)) if values else None


def figure_blocks(uri: str, runs: Sequence[Mapping[str, Any]], folder: Path, url: UrlFn) -> list[Block]:
    """Section 6: learning curves, policy maps, predicted vs true, Optuna, equations."""
    figs = folder / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    out: list[Block] = [Heading(2, "6. Figures")]
    out += _transfer_blocks(uri, runs, folder, url)
    out += _real_steps_blocks(uri, runs, folder)
    out += _fit_blocks(uri, runs, folder, url)
    out += _study_blocks(uri, runs, folder, url)
    _cleanup(folder / ".dl")
    for d in folder.glob("figures/.dl-*"):
        _cleanup(d)
    return out


def _transfer_blocks(uri: str, runs: Sequence[Mapping[str, Any]], folder: Path, url: UrlFn) -> list[Block]:
    """Learning curves pooled across seeds and one run's policy maps, per (env, surrogate kind)."""
    figs = folder / "figures"
    out: list[Block] = [Heading(3, "Learning curves and policy maps")]
    # runs that trained one arm alone (a Dyna benchmark's real arm) are the Dyna section's
    done = [r for r in rt.finished(runs, "transfer") if "," in r["tags"].get("arms", "surrogate,real")]

    def group(r: Mapping[str, Any]) -> tuple[str, str, str]:  # the zoo recipe and a fast one never share a plot
        return r["tags"].get("env", "?"), r["tags"].get("surrogate", "sindy"), r["tags"].get("agent", "?")

    groups = sorted({group(r) for r in done})
    if not groups:
        out.append(Para("RL transfer: not run (no finished transfer runs of both arms)."))
    for env, kind, agent in groups:
        members = [r for r in done if group(r) == (env, kind, agent)]
        label = f"{env}, {agent}, {kind}"
        bands = {arm: rt.curve_band(_curves(uri, members, arm, folder / ".dl")) for arm in rt.ARMS}
        if any(len(b) for b in bands.values()):
            path = figs / f"curves_{env}_{agent}_{kind}.png"
            path.write_bytes(learning_curve_figure(bands, f"{label} surrogate vs real", _solved_threshold(members)))
            out.append(Image(path, f"{label}: real return vs training steps, mean across seeds, shaded min..max"))
        else:
            out.append(Para(f"{label}: learning curves missing from runs {', '.join(r['run_id'][:8] for r in members)}."))
        first = members[0]["run_id"]
        got = _fetch(uri, first, "figures/policy_maps.png", figs / f"policy_maps_{env}_{agent}_{kind}.png")
        if got:
            out.append(Image(got, f"{label}: policy maps, real-trained vs surrogate-trained agent (run {first[:8]})"))
            out.append(Para(f"Policy maps from run {_ref(first, url)}."))
        else:
            out.append(Para(f"{label}: policy maps missing from run {_ref(first, url)}."))
    return out


def real_steps_figure(arms: Mapping[str, Sequence[pd.DataFrame]], title: str, solved: float | None) -> bytes:
    """Real return vs real steps, all counted (log axis), one line per seed and one colour per
    arm: the methods' costs differ by orders of magnitude, and their seeds' x values differ."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 3.8))
    ax = fig.subplots()
    for i, (arm, curves) in enumerate(arms.items()):
        color = f"C{i}"
        for j, c in enumerate(curves):
            ax.plot(c["real_steps"], c["return_mean"], color=color, lw=1, marker=".", ms=3, alpha=0.8,
                    label=f"{arm} (n={len(curves)} seeds)" if j == 0 else None)
    if solved is not None:
        ax.axhline(solved, ls="--", color="gray", lw=1, label=f"solved ({solved:g})")
    ax.set_xscale("log")
    ax.set_xlabel("real steps, all counted (model data, collections, evaluations that stop or select)")
    ax.set_ylabel("real return (the arm's own evaluations)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: the curves fill the axes
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")  # the legend outside the axes
    return buf.getvalue()


def _all_counted(uri: str, run: Mapping[str, Any], tmp: Path) -> pd.DataFrame | None:
    """One run's curve against its real steps so far, all counted: a Dyna run's (its curve's x
    already counts every real step of the loop); a real arm's training steps plus its evaluations
    so far (each point's share of ``real/eval_steps``)."""
    if run["tags"].get("sdrl.kind") == "dyna":
        got = _curves(uri, [run], "dyna", tmp)
        return got[0].rename(columns={"real_transitions": "real_steps"}) if got else None
    got = _curves(uri, [run], "real", tmp)
    if not got or not len(got[0]):
        return None
    c = got[0]
    per_point = float(run["metrics"].get("real/eval_steps", 0.0)) / len(c)
    return c.assign(real_steps=c["train_steps"] + per_point * (pd.RangeIndex(len(c)) + 1))


def _real_steps_blocks(uri: str, runs: Sequence[Mapping[str, Any]], folder: Path) -> list[Block]:
    """Per env with Dyna runs: every arm of section 5 as real return vs real steps, all counted."""
    dy = rt.dyna_table(runs)
    if dy.empty:
        return []
    out: list[Block] = [Heading(3, "Real return vs real steps, all counted (section 5's arms)")]
    by_id = {r["run_id"]: r for r in runs}
    for env in dy["env"].unique():
        arms = {}
        for _, row in dy[dy["env"] == env].iterrows():
            curves = [c for rid in row["runs"] if (c := _all_counted(uri, by_id[rid], folder / ".dl")) is not None]
            if curves:
                arms[f"{row['method']} ({row['agent']})"] = curves
        if not arms:
            continue
        path = folder / "figures" / f"real_steps_{env}.png"
        members = [by_id[rid] for rids in dy[dy["env"] == env]["runs"] for rid in rids]
        path.write_bytes(real_steps_figure(arms, f"{env}: every arm in real steps", _solved_threshold(members)))
        out.append(Image(path, f"{env}: real return vs real steps, all counted, one line per seed (Dyna: its screens; "
                               "real arms: their evaluations)"))
    return out


def _fit_blocks(uri: str, runs: Sequence[Mapping[str, Any]], folder: Path, url: UrlFn) -> list[Block]:
    """Predicted vs true of each env's main fit per model kind, and the SINDy equations."""
    figs = folder / "figures"
    out: list[Block] = [Heading(3, "Predicted vs true, and the discovered equations")]
    records = rt.fit_records(runs)
    any_fit = False
    for env in rt.envs_of(records):
        for kind in rt.surrogate_kinds({"tags": {"surrogate": r.get("surrogate", "sindy")}} for r in records):
            fits = rt.main_fits(records, env, kind)
            if not fits:
                continue
            any_fit = True
            rid = fits[0]["run_id"]
            got = _fetch(uri, rid, "figures/predicted_vs_true.png", figs / f"pred_{env}_{kind}.png")
            if got:
                out.append(Image(got, f"{env} ({kind}, {fits[0]['library'] if kind == 'sindy' else kind}): predicted vs true "
                                      f"on {fits[0]['test_set']} (run {rid[:8]})"))
            if kind == "sindy":
                eq = tracking.download_artifact(uri, rid, "model/equations.txt", folder / ".dl" / rid)
                if eq is not None and eq.is_file():
                    lines = [line for line in eq.read_text().splitlines() if line.strip()]
                    out.append(Equations(f"{env}: SINDy equations ({fits[0]['library']}), run {rid}", lines))
                else:
                    out.append(Para(f"{env}: equations missing from run {_ref(rid, url)}."))
    if not any_fit:
        out.append(Para("Fits: not run (no finished fit runs)."))
    return out


def _study_blocks(uri: str, runs: Sequence[Mapping[str, Any]], folder: Path, url: UrlFn) -> list[Block]:
    """Each Optuna study's history and Pareto figures, with its best error."""
    figs = folder / "figures"
    out: list[Block] = [Heading(3, "Hyperparameter search (Optuna)")]
    studies = [r for r in runs if r["tags"].get("sdrl.kind") == "study"]
    if not studies:
        out.append(Para("Optuna search: not run (no study runs in this selection)."))
    for s in studies:
        name = s["tags"].get("sdrl.study", s["run_id"][:8])
        for art, label in (("figures/optimization_history.png", "optimization history"), ("figures/pareto_front.png", "Pareto front")):
            got = _fetch(uri, s["run_id"], art, figs / f"study_{name}_{Path(art).stem}.png")
            if got:
                out.append(Image(got, f"study {name}: {label} (run {s['run_id'][:8]}, {s['status']})"))
        best = s["metrics"].get("best_error")
        out.append(Para(f"Study `{name}` (run {_ref(s['run_id'], url)}, {s['status']}): best error "
                        f"{'not run' if best is None else f'{best:.3e}'}, {int(s['metrics'].get('n_trials', 0))} trials."))
    return out


def _cleanup(path: Path) -> None:
    import shutil

    shutil.rmtree(path, ignore_errors=True)
