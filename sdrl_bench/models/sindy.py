"""SINDy dynamics model: a pysindy DiscreteSINDy fit, compiled into a batched numpy evaluator.

pysindy's ``predict`` costs about a millisecond a call, so the fitted model is compiled: its
active library terms become a structured feature program (``libraries`` compiles them, ``terms``
evaluates them), and prediction is that feature matrix times the coefficient matrix (in blocks
that keep OpenBLAS on one thread, ``models.blas``). The compiled evaluator is checked against
pysindy's ``predict`` on the training inputs at fit time. An equation that holds to the data's
float precision then has its coefficients snapped to the shortest decimals the data cannot
reject (``models.snap``): MountainCar's law comes out as 0.0015, not 0.0014999988. The model
saves as JSON data.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path
from collections.abc import Sequence

import numpy as np
import pysindy as ps
from pysindy.feature_library.base import BaseFeatureLibrary

from sdrl_bench import ConfigError
from sdrl_bench.models.base import read_model_json, seeded_global_numpy, write_model_json
from sdrl_bench.models.blas import matmul_rows
from sdrl_bench.models.libraries import compile_terms
from sdrl_bench.models.snap import ALPHA, prune_exact, snap_equation
from sdrl_bench.models.terms import evaluate_terms, validate_terms

FORMAT = "sdrl-bench/sindy-model-v1"


def sr3_l0(threshold: float, relax_coeff_nu: float = 1.0, **kwargs) -> ps.SR3:
    """pysindy's SR3 with an L0 penalty that thresholds at ``threshold``, the env's
    ``env.sindy.threshold`` as STLSQ reads it (``optimizer=sr3``). pysindy's SR3 takes the
    penalty's weight, not the threshold; its ``SR3.calculate_l0_weight`` converts (threshold**2 /
    (2 nu)), and a config cannot call it, hence this function. Given the threshold as the weight,
    MountainCar's SR3 thresholded at sqrt(2 x 0.003) = 0.077 and dropped the action's term."""
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not threshold >= 0:
        raise ConfigError(f"optimizer.threshold: a number >= 0 is required, got {threshold!r}")
    if isinstance(relax_coeff_nu, bool) or not isinstance(relax_coeff_nu, (int, float)) or not relax_coeff_nu > 0:
        raise ConfigError(f"optimizer.relax_coeff_nu: a number > 0 is required, got {relax_coeff_nu!r}")
    return ps.SR3(reg_weight_lam=ps.SR3.calculate_l0_weight(float(threshold), float(relax_coeff_nu)),
                  regularizer="L0", relax_coeff_nu=float(relax_coeff_nu), **kwargs)


class SindyModel:
    """s_{t+1} = Xi Theta(s_t, c_t) for regressed states s and controls c (actions, exogenous).

    Parameters
    ----------
    library : an unfitted pysindy feature library over inputs [states..., controls...].
    optimizer : an unfitted pysindy optimizer; cloned for every fit.
    seed : seeds numpy's global RNG during the fit (pysindy's ensembles draw from it).
    snap_alpha : level of the test that decides how far an exact law's coefficients are rounded
        (``models.snap.snap_equation``); None keeps the fitted coefficients as they are.
    snap_rtol : an equation counts as exact (and may be snapped) when its residual RMS is at most
        this fraction of its target's RMS.
    """

    kind = "sindy"
    summary_file = "equations.txt"

    def __init__(self, library: BaseFeatureLibrary | None, optimizer=None, seed: int = 0,
                 snap_alpha: float | None = ALPHA, snap_rtol: float = 1e-6):
        if snap_alpha is not None and not 0.0 < float(snap_alpha) < 1.0:
            raise ConfigError(f"surrogate.model.snap_alpha must be in (0, 1) or null, got {snap_alpha!r}")
        if not isinstance(snap_rtol, (int, float)) or not snap_rtol > 0.0:
            raise ConfigError(f"surrogate.model.snap_rtol must be positive, got {snap_rtol!r}")
        self.library = library
        self.optimizer = optimizer
        self.seed = seed
        self.snap_alpha = None if snap_alpha is None else float(snap_alpha)
        self.snap_rtol = float(snap_rtol)

    # ------------------------------------------------------------------ fit
    def fit(
        self,
        x: np.ndarray,
        u: np.ndarray,
        x_next: np.ndarray,
        *,
        state_names: Sequence[str],
        control_names: Sequence[str],
        bounds: dict[str, tuple[float, float]] | None = None,
    ) -> SindyModel:
        """Fit on rows (x_t, u_t) -> x_{t+1}; rows are independent (``x_next`` is explicit).
        ``bounds`` is not used: an ordinary library composes no next values."""
        x, u, x_next = (np.asarray(a, dtype=float) for a in (x, u, x_next))
        names = list(state_names) + list(control_names)
        if x.shape[1] != len(state_names) or u.shape[1] != len(control_names):
            raise ValueError("x / u columns do not match state_names / control_names")
        self._check_columns(x, u, names)
        t0, c0 = time.perf_counter(), time.process_time()
        with seeded_global_numpy(self.seed):
            sindy = ps.DiscreteSINDy(
                optimizer=copy.deepcopy(self.optimizer) if self.optimizer is not None else ps.STLSQ(),
                feature_library=copy.deepcopy(self.library),
            )
            sindy.fit(x, t=1, x_next=x_next, u=u, feature_names=names)
        self.fit_wall_seconds_ = time.perf_counter() - t0
        self.fit_cpu_seconds_ = time.process_time() - c0
        self.state_names_ = list(state_names)
        self.control_names_ = list(control_names)
        self.coef_ = np.asarray(sindy.coefficients(), dtype=float)
        self.feature_names_ = list(sindy.get_feature_names())
        self.terms_ = compile_terms(sindy.feature_library, len(names))
        self.n_fit_samples_ = len(x)
        self.library_description_ = repr(self.library)
        self.optimizer_description_ = repr(self.optimizer)
        self._compile()
        reference = np.asarray(sindy.predict(x, u=u))
        self.compile_max_abs_diff_ = float(np.max(np.abs(self.predict(x, u) - reference)))
        scale = max(1.0, float(np.max(np.abs(reference))))
        if not self.compile_max_abs_diff_ <= 1e-9 * scale:
            # ArithmeticError: an ill-conditioned candidate (huge rational coefficients) fails its
            # search trial, not the study; a plain fit stops here with this message
            raise ArithmeticError(
                f"compiled SINDy evaluator differs from pysindy.predict by {self.compile_max_abs_diff_:g}"
            )
        self._snap(np.concatenate([x, u], axis=1), x_next)
        return self

    def _snap(self, z: np.ndarray, x_next: np.ndarray) -> None:
        """Prune each exact equation to its smallest exact support, then round its coefficients (see
        ``models.snap``); ``snap_digits_`` holds
        the significant digits kept per equation (0: left as fitted)."""
        self.snap_digits_ = [0] * len(self.state_names_)
        if self.snap_alpha is None:
            return
        changed = False
        for i, row in enumerate(self.coef_):
            active = np.flatnonzero(row)
            theta = evaluate_terms([self.terms_[k] for k in active], z)
            kept, coef = prune_exact(theta, x_next[:, i], self.snap_rtol)
            if len(kept) < len(active):  # an exact law on fewer terms: refitted on them
                changed = True
                row[active] = 0.0
                active, theta = active[kept], theta[:, kept]
                row[active] = coef
            row[active], self.snap_digits_[i] = snap_equation(
                theta, x_next[:, i], row[active], self.snap_alpha, self.snap_rtol)
        if changed or any(self.snap_digits_):
            self._compile()

    def _check_columns(self, x: np.ndarray, u: np.ndarray, names: list[str]) -> None:
        """normalize_columns divides by each library column's norm: an all-zero column (a leg
        contact never seen, an action never taken) would turn every coefficient into NaN."""
        opt = getattr(self.optimizer, "opt", self.optimizer)
        if not getattr(opt, "normalize_columns", False):
            return
        lib = copy.deepcopy(self.library)
        theta = np.asarray(lib.fit_transform(np.concatenate([x, u], axis=1)))
        zero = np.flatnonzero(~np.any(theta != 0, axis=0))
        if len(zero):
            feature = lib.get_feature_names(names)[zero[0]]
            raise ConfigError(
                f"optimizer.normalize_columns: library column '{feature}' is all zeros in the "
                "training data; set optimizer.normalize_columns=false or collect more data"
            )

    def _compile(self) -> None:
        if len(self.terms_) != self.coef_.shape[1]:
            raise ValueError(f"{len(self.terms_)} terms for {self.coef_.shape[1]} coefficient columns")
        self._active = np.flatnonzero(np.any(self.coef_ != 0, axis=0))
        self._active_terms = [self.terms_[i] for i in self._active]
        self._active_coef_t = np.ascontiguousarray(self.coef_[:, self._active].T)

    # ------------------------------------------------------------------ use
    @property
    def n_active_terms(self) -> int:
        """Number of nonzero coefficients (summed over equations)."""
        return int(np.count_nonzero(self.coef_))

    @property
    def n_inputs(self) -> int:
        return len(self.state_names_) + len(self.control_names_)

    def features(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The full library matrix Theta (N, n_features), for inspection and tests."""
        return evaluate_terms(self.terms_, np.concatenate([np.atleast_2d(x), np.atleast_2d(u)], axis=1))

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next regressed states (N, n_states) for states (N, n_states) and controls (N, n_controls)."""
        z = np.concatenate([np.atleast_2d(x), np.atleast_2d(u)], axis=1)
        return matmul_rows(evaluate_terms(self._active_terms, z), self._active_coef_t)

    def equations(self, precision: int = 6) -> list[str]:
        """One line per regressed state: ``x[k+1] = c1 term1 + c2 term2 ...`` (nonzero terms)."""
        lines = []
        for name, row in zip(self.state_names_, self.coef_, strict=True):
            parts = [f"{c:+.{precision}g} {n}" if n != "1" else f"{c:+.{precision}g}"
                     for c, n in zip(row, self.feature_names_, strict=True) if c != 0]
            rhs = " ".join(parts) if parts else "0"
            lines.append(f"{name}[k+1] = {rhs.lstrip('+')}")
        return lines

    def describe(self) -> str:
        """The discovered equations, one per line."""
        return "\n".join(self.equations()) + "\n"

    def summary_metrics(self) -> dict[str, float]:
        return {
            "n_library_terms": float(self.coef_.shape[1]),
            "n_active_terms": float(self.n_active_terms),
            "n_parameters": float(self.n_active_terms),
            "compile_max_abs_diff": float(getattr(self, "compile_max_abs_diff_", 0.0)),
            "n_snapped_equations": float(sum(d > 0 for d in self.snap_digits_)),
            **{f"snap_digits/{s}": float(d) for s, d in zip(self.state_names_, self.snap_digits_, strict=True)},
        }

    def coefficients_by_name(self) -> dict[str, dict[str, float]]:
        """{state: {feature name: coefficient}} for the nonzero coefficients."""
        return {
            s: {n: float(c) for n, c in zip(self.feature_names_, row, strict=True) if c != 0}
            for s, row in zip(self.state_names_, self.coef_, strict=True)
        }

    # ------------------------------------------------------------------ persistence (data only)
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "kind": self.kind,
            "state_names": self.state_names_,
            "control_names": self.control_names_,
            "feature_names": self.feature_names_,
            "terms": [[list(f) for f in t] for t in self.terms_],
            "coefficients": self.coef_.tolist(),
            "library": self.library_description_,
            "optimizer": self.optimizer_description_,
            "n_fit_samples": self.n_fit_samples_,
            "snap_digits": list(self.snap_digits_),
        }

    def save(self, path: str | Path) -> Path:
        return write_model_json(path, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict, source: str = "model") -> SindyModel:
        try:
            if d.get("format") != FORMAT:
                raise ValueError(f"format is {d.get('format')!r}, expected {FORMAT!r}")
            model = cls(library=None)
            model.state_names_ = [str(s) for s in d["state_names"]]
            model.control_names_ = [str(s) for s in d["control_names"]]
            model.feature_names_ = [str(s) for s in d["feature_names"]]
            model.terms_ = validate_terms(d["terms"], model.n_inputs)
            model.coef_ = np.asarray(d["coefficients"], dtype=float)
            if model.coef_.shape != (len(model.state_names_), len(model.terms_)):
                raise ValueError(f"coefficients have shape {model.coef_.shape}")
            if len(model.feature_names_) != len(model.terms_) or not np.all(np.isfinite(model.coef_)):
                raise ValueError("feature names or coefficients are inconsistent")
            model.library_description_ = str(d.get("library", ""))
            model.optimizer_description_ = str(d.get("optimizer", ""))
            model.n_fit_samples_ = int(d.get("n_fit_samples", 0))
            digits = d.get("snap_digits", [0] * len(model.state_names_))  # absent in older files
            model.snap_digits_ = [int(v) for v in digits]
            if len(model.snap_digits_) != len(model.state_names_):
                raise ValueError(f"snap_digits has {len(digits)} entries for {len(model.state_names_)} states")
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: not a valid SINDy model file ({exc})") from exc
        model._compile()
        return model

    @classmethod
    def from_saved(cls, data: dict, path: Path) -> SindyModel:
        """The loader ``models.base.load_model`` calls with the JSON object of ``path``."""
        return cls.from_dict(data, source=str(path))

    @classmethod
    def load(cls, path: str | Path) -> SindyModel:
        return cls.from_dict(read_model_json(path), source=str(path))
