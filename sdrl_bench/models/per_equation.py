"""Per-equation sparse regression: each regressed state gets its own candidate terms.

A per-equation library is data, written in a library YAML (``conf/library/*.yaml``) as the one
part of ``library.parts``::

    parts:
      - library:
          _target_: sdrl_bench.models.per_equation.PerEquationLibrary
          form: delta            # fit s'_i - s_i (default) or next: fit s'_i itself
          threshold: 3.0e-4      # STLSQ threshold for every equation (null: the optimizer's own)
          thresholds: {x: 0.0}   # per-equation overrides
          noise_by: [a_main]     # residual covariance per one-hot control (the step's noise)
          equations:
            v: [bias, u, sin(p)]
            p: ["v'"]            # a primed state is its *next* value (semi-implicit Euler)

Term syntax: factors joined by ``*``; a factor is ``bias`` (or ``1``: the constant), ``NAME``,
``NAME^k`` (k in 1..4), ``sin(NAME)``, ``cos(NAME)``, ``rat(NAME)``, ``xrat(NAME)`` (the ops
of ``models.terms``); ``NAME`` is a model input (a regressed state, an exogenous state, an
action column) and a regressed state may be primed. Primed references fix an evaluation order;
a cycle is an error. Every error is one line naming the key (``library.equations.v[2]``).
Syntax is checked when the library is built; names when it meets an env (``check_inputs``,
before any data is collected).

Fitting: one fresh copy of the configured pysindy optimizer per equation, on that equation's
own feature matrix (primed factors read the *observed* next values). The fitted model is then
**flattened**: each primed factor is replaced by its equation's expansion, which gives an
ordinary term list and coefficient matrix (``terms_``, ``coef_``, as ``SindyModel`` has), so the
compiled evaluators (``models.fast``) and the surrogate's batched step use it unchanged. The
printed equations keep the per-equation form (``x' = x + 0.01 vx'``). Saved as JSON data
(format ``sdrl-bench/per-equation-v1``): terms as text and coefficients, never code.

Optional extras, both stored in the file: ``noise_`` ({control: covariance of the fit residuals
on rows where that one-hot control is 1}: the surrogate adds it to its step, ``surrogate.env``)
and ``members_`` (``ensemble`` > 1: coefficient matrices refitted on bootstrap resamples; their
disagreement is the surrogate's uncertainty penalty).

Over the project's ~300-line habit: the library's validation, the per-equation fit and the
model (describe, save, load, flattening for the compiled evaluators) share one term syntax;
splitting the library from the model is the next tidy-up.
"""

from __future__ import annotations

import copy
import json
import re
import time
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np
import pysindy as ps
from pysindy.feature_library.base import BaseFeatureLibrary, x_sequence_or_item

from sdrl_bench import ConfigError
from sdrl_bench.models.base import read_model_json, residual_noise, seeded_global_numpy, write_model_json
from sdrl_bench.models.blas import matmul_rows
from sdrl_bench.models.snap import ALPHA, snap_equation
from sdrl_bench.models.terms import TABLE, Term, evaluate_terms

FORMAT = "sdrl-bench/per-equation-v1"
_FUNCS = ("sin", "cos", "rat", "xrat")
_FACTOR = re.compile(r"^(?:(" + "|".join(_FUNCS) + r")\((\w+'?)\)|(\w+'?)(?:\^(\d+))?)$")
# A parsed factor: (name, op, power, primed); op is a models.terms op ("pow" for NAME^k).
PFactor = tuple[str, str, int, bool]


def parse_term(text: Any, key: str) -> tuple[PFactor, ...]:
    """One term's factors (the constant: ``()``); ``key`` names it in errors."""
    if not isinstance(text, str) or not text.strip():
        raise ConfigError(f"{key}: a term must be a non-empty string, got {text!r}")
    s = text.replace(" ", "")
    if s in ("bias", "1"):
        return ()
    factors = []
    for part in s.split("*"):
        m = _FACTOR.match(part)
        if not m:
            raise ConfigError(f"{key}: cannot parse factor {part!r} of term {text!r} (expected NAME, NAME^k, "
                              f"{'/'.join(_FUNCS)}(NAME), NAME' or bias)")
        func, fname, name, power = m.groups()
        op, name = (func, fname) if func else ("pow", name)
        p = int(power) if power else 1
        if not 1 <= p <= 4:
            raise ConfigError(f"{key}: power {p} in term {text!r} is outside 1..4")
        factors.append((name.rstrip("'"), op, p, name.endswith("'")))
    return tuple(factors)


def term_text(factors: Sequence[PFactor]) -> str:
    if not factors:
        return "1"
    out = []
    for name, op, p, primed in factors:
        n = name + ("'" if primed else "")
        out.append(f"{op}({n})" if op != "pow" else (n if p == 1 else f"{n}^{p}"))
    return "*".join(out)


class PerEquationLibrary(BaseFeatureLibrary):
    """A per-equation library (see the module docstring); syntax is validated here."""

    def __init__(self, equations: dict | None = None, form: str = "delta", threshold: float | None = None,
                 thresholds: dict | None = None, noise_by: Sequence[str] = (), ensemble: int = 1,
                 key: str = "library"):
        self.equations, self.form, self.threshold = equations, form, threshold
        self.thresholds, self.noise_by, self.ensemble, self.key = thresholds, noise_by, ensemble, key
        if not isinstance(equations, dict) or not equations:
            raise ConfigError(f"{key}.equations: a mapping regressed state -> list of terms is required")
        if form not in ("delta", "next"):
            raise ConfigError(f"{key}.form: expected 'delta' or 'next', got {form!r}")
        self.parsed: dict[str, tuple[tuple[PFactor, ...], ...]] = {}
        for t, terms in equations.items():
            if terms is None or (isinstance(terms, (list, tuple)) and not terms):
                raise ConfigError(f"{key}.equations.{t}: an equation needs at least one term")
            if not isinstance(terms, (list, tuple)):
                raise ConfigError(f"{key}.equations.{t}: expected a list of terms, got {type(terms).__name__}")
            parsed = tuple(parse_term(s, f"{key}.equations.{t}[{i}]") for i, s in enumerate(terms))
            texts = [term_text(p) for p in parsed]
            dup = sorted({x for x in texts if texts.count(x) > 1})
            if dup:
                raise ConfigError(f"{key}.equations.{t}: duplicate term {dup[0]!r}")
            self.parsed[str(t)] = parsed
        for name, value in [("threshold", threshold), *((f"thresholds.{k}", v) for k, v in (thresholds or {}).items())]:
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not np.isfinite(value) or value < 0):
                raise ConfigError(f"{key}.{name}: a number >= 0 is required, got {value!r}")
        for k in thresholds or {}:
            if k not in self.parsed:
                raise ConfigError(f"{key}.thresholds.{k}: not a state with an equation ({', '.join(self.parsed)})")
        if isinstance(ensemble, bool) or not isinstance(ensemble, int) or ensemble < 1:
            raise ConfigError(f"{key}.ensemble: a positive integer is required, got {ensemble!r}")
        self.order = self._order()

    def _order(self) -> tuple[str, ...]:
        deps = {t: {f[0] for term in eq for f in term if f[3]} for t, eq in self.parsed.items()}
        for t, d in deps.items():
            bad = sorted(d - set(self.parsed))
            if bad:
                i, term = next((i, term) for i, term in enumerate(self.parsed[t]) if any(f[3] and f[0] == bad[0] for f in term))
                raise ConfigError(f"{self.key}.equations.{t}[{i}]: {bad[0]}' (a next value) names {bad[0]!r}, "
                                  "which is not a regressed state")
        done: list[str] = []
        while len(done) < len(deps):
            ready = [t for t in deps if t not in done and deps[t] <= set(done)]
            if not ready:
                left = [t for t in deps if t not in done]
                raise ConfigError(f"{self.key}.equations: next-value references form a cycle among {', '.join(left)}")
            done += ready
        return tuple(done)

    def check_inputs(self, state_names: Sequence[str], control_names: Sequence[str]) -> None:
        """Names against an env's regressed states and model inputs (one-line errors)."""
        states, inputs, key = list(state_names), list(state_names) + list(control_names), self.key
        for t in self.parsed:
            if t not in states:
                raise ConfigError(f"{key}.equations.{t}: not a regressed state; regressed: {', '.join(states)}")
        missing = [t for t in states if t not in self.parsed]
        if missing:
            raise ConfigError(f"{key}.equations: no equation for regressed state(s) {', '.join(missing)}")
        for t, eq in self.parsed.items():
            for i, term in enumerate(eq):
                for name, *_ in term:
                    if name not in inputs:
                        raise ConfigError(f"{key}.equations.{t}[{i}]: unknown name {name!r} in term "
                                          f"{term_text(term)!r}; known: {', '.join(inputs)}")
        for c in self.noise_by:
            if c not in control_names:
                raise ConfigError(f"{key}.noise_by: {c!r} is not a control input ({', '.join(control_names)})")

    @property
    def n_terms(self) -> int:
        return sum(len(eq) for eq in self.parsed.values())

    # pysindy's library protocol: enough for composition and counting (``libraries.count_features``)
    @x_sequence_or_item
    def fit(self, x_full, y=None):
        self.n_features_in_ = x_full[0].shape[x_full[0].ax_coord]
        self.n_output_features_ = self.n_terms
        return self

    def transform(self, x_full):
        raise ConfigError(f"{self.key}: a per-equation library is fitted by its own model; "
                          "fit it with surrogate=sindy (sdrl_bench.models.per_equation.sparse_model)")

    def get_feature_names(self, input_features=None):
        return [f"{t}:{term_text(term)}" for t, eq in self.parsed.items() for term in eq]


def _find_library(library: Any) -> PerEquationLibrary | None:
    if isinstance(library, PerEquationLibrary):
        return library
    for lib in getattr(library, "libraries", None) or ():
        found = _find_library(lib)
        if found is not None:
            return found
    return None


def sparse_model(library: Any, optimizer: Any = None, seed: int = 0, **kwargs: Any):
    """The sparse-regression model a library asks for: ``PerEquationModel`` for a per-equation
    library, else ``SindyModel`` (the factory of ``surrogate=sindy``)."""
    if _find_library(library) is not None:
        return PerEquationModel(library, optimizer, seed, **kwargs)
    from sdrl_bench.models.sindy import SindyModel  # noqa: PLC0415

    return SindyModel(library, optimizer, seed, **kwargs)


Expansion = dict[Term, float]


def _canon(factors: Sequence[tuple[int, str, float]]) -> Term:
    return tuple(sorted(factors))


class PerEquationModel:
    """s'_i = [s_i +] sum_k c_ik theta_ik(s, c, s') per equation; see the module docstring.

    Parameters
    ----------
    library : a ``PerEquationLibrary`` (or a pysindy library composition holding one).
    optimizer : an unfitted pysindy optimizer, copied fresh for every equation (and every
        ensemble member); the library's threshold, when given, is set on each copy.
    seed : seeds the bootstrap resamples of the ensemble.
    snap_alpha, snap_rtol : as for ``SindyModel`` (exact equations only).
    """

    kind = "per_equation"
    summary_file = "equations.txt"

    def __init__(self, library: Any = None, optimizer: Any = None, seed: int = 0,
                 snap_alpha: float | None = ALPHA, snap_rtol: float = 1e-6):
        lib = _find_library(library) if library is not None else None
        if library is not None and lib is None:
            raise ConfigError("library: the per-equation model needs a per-equation library "
                              "(library.parts[0].library._target_: sdrl_bench.models.per_equation.PerEquationLibrary)")
        self.library, self.optimizer, self.seed = lib, optimizer, int(seed)
        self.snap_alpha = None if snap_alpha is None else float(snap_alpha)
        self.snap_rtol = float(snap_rtol)

    def check_inputs(self, state_names: Sequence[str], control_names: Sequence[str]) -> None:
        self.library.check_inputs(state_names, control_names)

    # ------------------------------------------------------------------ fit
    def _optimizer(self, target: str):
        opt = copy.deepcopy(self.optimizer) if self.optimizer is not None else ps.STLSQ(threshold=0.0, alpha=0.0)
        lib = self.library
        thr = (lib.thresholds or {}).get(target, lib.threshold)
        if thr is not None:
            target_opt = getattr(opt, "opt", opt)  # an EnsembleOptimizer wraps the thresholding one
            if hasattr(target_opt, "threshold"):
                target_opt.threshold = float(thr)
        return opt

    def _features(self, target: str, z: np.ndarray, z_next: np.ndarray) -> np.ndarray:
        """Feature matrix of one equation; primed factors read ``z_next`` (N, n_states)."""
        cols = []
        for term in self._terms[target]:
            c = np.ones(len(z))
            for j, op, p, primed in term:
                v = z_next[:, j] if primed else z[:, j]
                c = c * (v ** p if op == "pow" else TABLE[op].column(1.0, v))
            cols.append(c)
        return np.column_stack(cols)

    def _bind(self, state_names: Sequence[str], control_names: Sequence[str],
              bounds: dict[str, Sequence[float]] | None = None) -> None:
        self.state_names_, self.control_names_ = list(state_names), list(control_names)
        names = self.state_names_ + self.control_names_
        primed = {f[0] for eq in self.library.parsed.values() for term in eq for f in term if f[3]}
        self.clipped_ = {s: (float(lo), float(hi)) for s, (lo, hi) in (bounds or {}).items()
                         if s in primed and (np.isfinite(lo) or np.isfinite(hi))}
        """{state: (low, high)}: primed references to these states read the bounded next value."""
        self._terms = {t: tuple(tuple((names.index(n) if not pr else self.state_names_.index(n), op, p, pr)
                                      for n, op, p, pr in term) for term in eq)
                       for t, eq in self.library.parsed.items()}

    def fit(self, x: np.ndarray, u: np.ndarray, x_next: np.ndarray, *, state_names: Sequence[str],
            control_names: Sequence[str], bounds: dict[str, tuple[float, float]] | None = None) -> PerEquationModel:
        """Fit each equation on its own features (primed factors read the observed next values,
        which the env has already bounded). ``bounds``: the env's bounds of regressed states; a
        primed reference to a bounded state then reads its next value *after* the bound, in
        ``predict`` and in the compiled evaluators (``clipped_``)."""
        x, u, x_next = (np.asarray(a, dtype=float) for a in (x, u, x_next))
        self.library.check_inputs(state_names, control_names)
        t0, c0 = time.perf_counter(), time.process_time()
        self._bind(state_names, control_names, bounds)
        z = np.concatenate([x, u], axis=1)
        with seeded_global_numpy(self.seed):  # an EnsembleOptimizer's resamples
            self.eq_coef_ = self._fit_rows(z, x_next)
        self.snap_digits_ = self._snap(z, x_next)
        self.n_fit_samples_ = len(x)
        self.library_description_ = json.dumps(self.library_config())
        self.optimizer_description_ = repr(self.optimizer)
        self.members_ = []
        member_coefs = []
        if self.library.ensemble > 1:
            rng = np.random.default_rng(self.seed)
            with seeded_global_numpy(self.seed):
                for _ in range(self.library.ensemble):
                    idx = rng.integers(len(z), size=len(z))
                    member_coefs.append(self._fit_rows(z[idx], x_next[idx]))
        self._member_coefs = member_coefs
        self._flatten(member_coefs)
        self.members_ = [self._flat_coef(c) for c in member_coefs]
        resid = x_next - self.predict(x, u)
        self.fit_mse_ = {s: float(np.mean(resid[:, i] ** 2)) for i, s in enumerate(self.state_names_)}
        self.noise_ = residual_noise(resid, z[:, len(self.state_names_):], self.control_names_, self.library.noise_by)
        self.fit_wall_seconds_ = time.perf_counter() - t0
        self.fit_cpu_seconds_ = time.process_time() - c0
        return self

    def _fit_rows(self, z: np.ndarray, x_next: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for t in self.library.parsed:
            i = self.state_names_.index(t)
            theta = self._features(t, z, x_next)
            y = x_next[:, i] - (z[:, i] if self.library.form == "delta" else 0.0)
            opt = self._optimizer(t)
            opt.fit(theta, y.reshape(-1, 1))
            out[t] = np.asarray(opt.coef_, dtype=float).reshape(-1)
        return out

    def _snap(self, z: np.ndarray, x_next: np.ndarray) -> dict[str, int]:
        digits = {t: 0 for t in self.library.parsed}
        if self.snap_alpha is None:
            return digits
        for t, c in self.eq_coef_.items():
            active = np.flatnonzero(c)
            if len(active):
                i = self.state_names_.index(t)
                y = x_next[:, i] - (z[:, i] if self.library.form == "delta" else 0.0)
                theta = self._features(t, z, x_next)[:, active]
                c[active], digits[t] = snap_equation(theta, y, c[active], self.snap_alpha, self.snap_rtol)
        return digits

    # ------------------------------------------------------------------ flattening
    @property
    def _n_inputs(self) -> int:
        return len(self.state_names_) + len(self.control_names_)

    def _extra_index(self, state: str) -> int:
        """The input column standing for the bounded next value of ``state`` (after the model's inputs)."""
        return self._n_inputs + list(self.clipped_).index(state)

    def _expansions(self, eq_coef: dict[str, np.ndarray]) -> dict[str, Expansion]:
        """Each equation as {term: coefficient} over plain (unprimed) terms, s'_i itself. A primed
        factor of a bounded state (``clipped_``) stays a factor: the input column of its bounded
        next value (``_extra_index``), filled stage by stage in ``predict``."""
        exp: dict[str, Expansion] = {}
        for s in self.clipped_:
            exp[f"{s}'"] = {((self._extra_index(s), "pow", 1.0),): 1.0}
        for t in self.library.order:
            i = self.state_names_.index(t)
            e: Expansion = {((i, "pow", 1.0),): 1.0} if self.library.form == "delta" else {}
            for c, term in zip(eq_coef[t], self._terms[t], strict=True):
                if c == 0.0:
                    continue
                plain = [(j, op, 1.0) for j, op, p, pr in term if not pr for _ in range(p)]
                parts: Expansion = {(): float(c)}
                for j, _, p, pr in term:
                    if pr:
                        name = self.state_names_[j]
                        sub = exp[f"{name}'"] if name in self.clipped_ else exp[name]
                        for _ in range(p):
                            parts = {_canon(a + b): ca * cb for a, ca in parts.items() for b, cb in sub.items()}
                for term2, v in parts.items():
                    key = _canon(plain + list(term2))
                    e[key] = e.get(key, 0.0) + v
            exp[t] = e
        return exp

    def _flatten(self, others: Sequence[dict[str, np.ndarray]] = ()) -> None:
        """``terms_`` (the union of the terms of this fit and of ``others``, e.g. ensemble
        members) and ``coef_`` of this fit."""
        exps = self._expansions(self.eq_coef_)
        terms: dict[Term, None] = {}
        for e in [exps, *(self._expansions(c) for c in others)]:
            for s in self.state_names_:
                for term in e[s]:
                    terms.setdefault(term, None)
        self.terms_ = list(terms)
        self.coef_ = self._flat_coef(self.eq_coef_, exps)
        self._active_coef_t = np.ascontiguousarray(self.coef_.T)
        self.stages_ = self._stages() if self.clipped_ else None

    def candidate_structure(self) -> tuple[list[Term], dict | None]:
        """(terms, stages) of every term a fit of this library can keep: the flattened table of
        the equations with every candidate coefficient non-zero, and its staged evaluation. Any
        fit's ``terms_`` is a subset, and these stages are a valid order for it (a row waits for
        every bounded value it could read). ``models.jax_eval.linear_predictor`` keys its compiled
        program on this, so Dyna's refits and other seeds of the same library share one program
        whatever terms each fit kept."""
        exps = self._expansions({t: np.ones_like(c) for t, c in self.eq_coef_.items()})
        terms = list(dict.fromkeys(term for s in self.state_names_ for term in exps[s]))
        index = {term: k for k, term in enumerate(terms)}
        pattern = np.zeros((len(self.state_names_), len(terms)))
        for i, s in enumerate(self.state_names_):
            pattern[i, [index[term] for term in exps[s]]] = 1.0
        return terms, self._stages(terms, pattern) if self.clipped_ else None

    def _stages(self, terms: Sequence[Term] | None = None, coef: np.ndarray | None = None) -> dict:
        """The staged evaluation a bounded prime needs (``models.fast`` reads it): ``n_inputs``,
        and per stage the output rows it computes and the bounds it then applies, {row, extra
        input column, low, high}. A row's stage follows the extra columns its terms read (of
        ``terms`` with ``coef`` non-zero; default the fit's ``terms_`` and ``coef_``)."""
        terms, coef = (self.terms_, self.coef_) if terms is None else (terms, coef)
        n, extra = self._n_inputs, {self._extra_index(s): s for s in self.clipped_}
        stage: dict[int, int] = {}
        rows_of = {i: {j for k, t in enumerate(terms) if coef[i, k] != 0 for j, *_ in t if j >= n}
                   for i in range(len(self.state_names_))}
        while len(stage) < len(rows_of):
            for i, needs in rows_of.items():
                src = [self.state_names_.index(extra[j]) for j in needs]
                if i not in stage and all(r in stage for r in src):
                    stage[i] = 1 + max((stage[r] for r in src), default=-1)
        out = []
        for k in range(max(stage.values()) + 1):
            rows = [i for i in stage if stage[i] == k]
            clips = [(self.state_names_.index(s), self._extra_index(s), *self.clipped_[s]) for s in self.clipped_
                     if stage[self.state_names_.index(s)] == k]
            out.append({"rows": rows, "clips": clips})
        return {"n_inputs": n, "stages": out}

    def _flat_coef(self, eq_coef: dict[str, np.ndarray], exps: dict[str, Expansion] | None = None) -> np.ndarray:
        exps = exps or self._expansions(eq_coef)
        index = {term: k for k, term in enumerate(self.terms_)} if hasattr(self, "terms_") else {}
        coef = np.zeros((len(self.state_names_), len(self.terms_)))
        for i, s in enumerate(self.state_names_):
            for term, v in exps[s].items():
                if term in index:
                    coef[i, index[term]] += v
        return coef

    # ------------------------------------------------------------------ use
    @property
    def n_active_terms(self) -> int:
        return int(sum(np.count_nonzero(c) for c in self.eq_coef_.values()))

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        z = np.concatenate([np.atleast_2d(x), np.atleast_2d(u)], axis=1)
        if self.stages_ is None:
            return matmul_rows(evaluate_terms(self.terms_, z), self._active_coef_t)
        return self._staged(z, self.coef_)

    def _staged(self, z: np.ndarray, coef: np.ndarray) -> np.ndarray:
        """Stage by stage: the rows of a stage, then the bounds of the states whose bounded next
        value a later stage reads (the env's own order: clip v', then x' = x + dt v')."""
        z_ext = np.concatenate([z, np.zeros((len(z), len(self.clipped_)))], axis=1)
        out = np.empty((len(z), len(self.state_names_)))
        for st in self.stages_["stages"]:
            rows = st["rows"]
            out[:, rows] = evaluate_terms(self.terms_, z_ext) @ coef[rows].T
            for i, col, lo, hi in st["clips"]:
                z_ext[:, col] = np.clip(out[:, i], lo, hi)
        return out

    def predict_members(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """(K, N, n_states) predictions of the ensemble members (K = 0 without an ensemble)."""
        z = np.concatenate([np.atleast_2d(x), np.atleast_2d(u)], axis=1)
        if self.stages_ is not None:
            return np.array([self._staged(z, np.asarray(m)) for m in self.members_]).reshape(len(self.members_), len(z), -1)
        theta = evaluate_terms(self.terms_, z)
        return np.array([theta @ np.asarray(m).T for m in self.members_]).reshape(len(self.members_), len(z), -1)

    def equations(self, precision: int = 4) -> list[str]:
        """One line per regressed state in the per-equation form, nonzero terms only."""
        lines = []
        for s in self.state_names_:
            parsed = self.library.parsed[s]
            parts = [f"{c:+.{precision}g}" + ("" if not term else f" {term_text(term)}")
                     for c, term in zip(self.eq_coef_[s], parsed, strict=True) if c != 0.0]
            lhs = f"{s}' = {s} " if self.library.form == "delta" else f"{s}' = "
            lines.append(lhs + (" ".join(parts) if parts else "+0"))
        return lines

    def describe(self) -> str:
        return "\n".join(self.equations()) + "\n"

    def coefficients_by_name(self) -> dict[str, dict[str, float]]:
        """{state: {term: coefficient}} for the nonzero coefficients, in the per-equation form
        (a delta equation's own state is implied, as in ``equations``; the bias is "1")."""
        return {s: {term_text(term) or "1": float(c) for c, term in zip(self.eq_coef_[s], self.library.parsed[s], strict=True)
                    if c != 0.0} for s in self.state_names_}

    def summary_metrics(self) -> dict[str, float]:
        return {
            "n_library_terms": float(self.library.n_terms),
            "n_active_terms": float(self.n_active_terms),
            "n_parameters": float(self.n_active_terms),
            "n_snapped_equations": float(sum(d > 0 for d in self.snap_digits_.values())),
            "n_ensemble_members": float(len(self.members_)),
        }

    # ------------------------------------------------------------------ persistence (data only)
    def library_config(self) -> dict:
        lib = self.library
        return {"form": lib.form, "equations": {t: [term_text(x) for x in eq] for t, eq in lib.parsed.items()},
                "noise_by": list(lib.noise_by), "ensemble": lib.ensemble}

    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "kind": self.kind,
            "state_names": self.state_names_, "control_names": self.control_names_,
            "library": self.library_config(),
            "coefficients": {t: [float(c) for c in v] for t, v in self.eq_coef_.items()},
            "snap_digits": self.snap_digits_, "noise": self.noise_,
            "members": [{t: [float(c) for c in v] for t, v in m.items()} for m in self._member_coefs],
            "optimizer": self.optimizer_description_, "n_fit_samples": self.n_fit_samples_,
            "bounds": {k: list(v) for k, v in self.clipped_.items()},
        }

    def save(self, path: str | Path) -> Path:
        return write_model_json(path, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict, source: str = "model") -> PerEquationModel:
        try:
            if d.get("format") != FORMAT:
                raise ValueError(f"format is {d.get('format')!r}, expected {FORMAT!r}")
            lc = d["library"]
            lib = PerEquationLibrary(equations=lc["equations"], form=lc["form"], noise_by=tuple(lc.get("noise_by", ())),
                                     ensemble=int(lc.get("ensemble", 1)), key=f"{source}: library")
            model = cls(lib)
            lib.check_inputs(d["state_names"], d["control_names"])
            model._bind(d["state_names"], d["control_names"], {k: tuple(v) for k, v in d.get("bounds", {}).items()})
            model.eq_coef_ = {t: np.asarray(d["coefficients"][t], dtype=float) for t in lib.parsed}
            for t, c in model.eq_coef_.items():
                if c.shape != (len(lib.parsed[t]),) or not np.all(np.isfinite(c)):
                    raise ValueError(f"coefficients of {t} do not match its {len(lib.parsed[t])} terms")
            model.snap_digits_ = {t: int(v) for t, v in d.get("snap_digits", {}).items()}
            model.noise_ = {str(k): np.asarray(v, dtype=float).tolist() for k, v in d.get("noise", {}).items()}
            model.optimizer_description_ = str(d.get("optimizer", ""))
            model.n_fit_samples_ = int(d.get("n_fit_samples", 0))
            model.library_description_ = json.dumps(lc)
            members = [{t: np.asarray(c, dtype=float) for t, c in m.items()} for m in d.get("members", [])]
            model._member_coefs = members
            model._flatten(members)
            model.members_ = [model._flat_coef(c) for c in members]
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: not a valid per-equation model file ({exc})") from exc
        return model

    @classmethod
    def from_saved(cls, data: dict, path: Path) -> PerEquationModel:
        return cls.from_dict(data, source=str(path))

    @classmethod
    def load(cls, path: str | Path) -> PerEquationModel:
        return cls.from_dict(read_model_json(path), source=str(path))

