"""Feature libraries: composition for an env's inputs, and compilation into structured terms.

A library config is a list of *parts*: a pysindy library object (instantiated as it is) and the
inputs it acts on: ``all`` (regressed states and controls), ``states`` (regressed states only:
trigonometric terms never touch actions or boolean leg contacts) or ``controls``.

Every output feature of a fitted library is compiled into a *term*: a product of factors
``(input index, op, parameter)``, the ops being those of ``models.terms`` (pow, sin, cos, rat,
xrat). Terms are plain data: a saved model is JSON, never code.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np
import pysindy as ps
from pysindy.feature_library.base import BaseFeatureLibrary, ConcatLibrary, x_sequence_or_item
from pysindy.utils import AxesArray, comprehend_axes

from sdrl_bench import ConfigError
from sdrl_bench.models.terms import Term, evaluate_terms


class _TermLibrary(BaseFeatureLibrary):
    """A pysindy library defined by structured terms (one factor per term, per input)."""

    def _unit_terms(self) -> list[tuple[str, float, str]]:  # (op, param, name pattern)
        raise NotImplementedError

    def terms_for(self, n_inputs: int) -> list[Term]:
        return [((j, op, p),) for op, p, _ in self._unit_terms() for j in range(n_inputs)]

    @x_sequence_or_item
    def fit(self, x_full, y=None):
        self.n_features_in_ = x_full[0].shape[x_full[0].ax_coord]
        self.n_output_features_ = len(self.terms_for(self.n_features_in_))
        return self

    @x_sequence_or_item
    def transform(self, x_full):
        terms = self.terms_for(self.n_features_in_)
        out = []
        for x in x_full:
            flat = np.asarray(x).reshape(-1, x.shape[-1])
            xp = evaluate_terms(terms, flat).reshape(*x.shape[:-1], len(terms))
            out.append(AxesArray(xp, comprehend_axes(xp)))
        return out

    def get_feature_names(self, input_features=None):
        names = input_features or [f"x{i}" for i in range(self.n_features_in_)]
        return [pat.format(x=names[j]) for _, _, pat in self._unit_terms() for j in range(len(names))]


class TrigLibrary(_TermLibrary):
    """sin(f x) and cos(f x) for every input x and every frequency f (any positive real)."""

    def __init__(self, frequencies: Sequence[float] = (1.0,), include_sin: bool = True, include_cos: bool = True):
        freqs = [float(f) for f in frequencies]
        if not freqs or any(not np.isfinite(f) or f <= 0 for f in freqs):
            raise ValueError(f"frequencies must be positive numbers, got {list(frequencies)}")
        if not (include_sin or include_cos):
            raise ValueError("include_sin and include_cos cannot both be False")
        self.frequencies = frequencies
        self.include_sin = include_sin
        self.include_cos = include_cos

    def _unit_terms(self):
        units = []
        for f in map(float, self.frequencies):
            if self.include_sin:
                units.append(("sin", f, f"sin({f:g} {{x}})"))
            if self.include_cos:
                units.append(("cos", f, f"cos({f:g} {{x}})"))
        return units


class RationalLibrary(_TermLibrary):
    """1/(1+x^2) and x/(1+x^2) for every input x: bounded rational terms with no poles."""

    def __init__(self, include_inverse: bool = True, include_ratio: bool = True):
        if not (include_inverse or include_ratio):
            raise ValueError("include_inverse and include_ratio cannot both be False")
        self.include_inverse = include_inverse
        self.include_ratio = include_ratio

    def _unit_terms(self):
        units = []
        if self.include_inverse:
            units.append(("rat", 1.0, "1/(1+{x}^2)"))
        if self.include_ratio:
            units.append(("xrat", 1.0, "{x}/(1+{x}^2)"))
        return units


# ---------------------------------------------------------------------- composition
@dataclass(frozen=True)
class LibraryPart:
    """One pysindy library and the inputs it acts on: 'all', 'states', 'controls', or a list of
    input names (e.g. ``[angle]``)."""

    library: BaseFeatureLibrary
    inputs: str | tuple[str, ...] = "all"


def build_library(
    parts: Sequence[LibraryPart | dict], state_names: Sequence[str], control_names: Sequence[str]
) -> ps.GeneralizedLibrary:
    """A GeneralizedLibrary over inputs [states..., controls...] from ``parts``."""
    if not parts:
        raise ConfigError("library.parts: at least one library part is needed")
    names = list(state_names) + list(control_names)
    n_states = len(state_names)
    groups = {
        "all": list(range(len(names))),
        "states": list(range(n_states)),
        "controls": list(range(n_states, len(names))),
    }
    libs, inputs = [], []
    for i, part in enumerate(parts):
        if isinstance(part, dict):
            part = LibraryPart(**part)
        if not isinstance(part.library, BaseFeatureLibrary):
            raise ConfigError(f"library.parts[{i}].library: not a pysindy feature library")
        if isinstance(part.inputs, str):
            if part.inputs not in groups:
                raise ConfigError(
                    f"library.parts[{i}].inputs: {part.inputs!r} is not one of {sorted(groups)} or a list of input names"
                )
            idx = groups[part.inputs]
        else:
            unknown = [n for n in part.inputs if n not in names]
            if unknown:
                raise ConfigError(f"library.parts[{i}].inputs: {unknown} are not inputs of this env ({names})")
            idx = [names.index(n) for n in part.inputs]
        if not idx:
            raise ConfigError(f"library.parts[{i}].inputs: selects no input for this env")
        libs.append(part.library)
        inputs.append(idx)
    return ps.GeneralizedLibrary(libs, inputs_per_library=inputs)


def count_features(library: BaseFeatureLibrary, n_inputs: int) -> int:
    """Number of output features ``library`` makes from ``n_inputs`` inputs (fits a clone)."""
    lib = copy.deepcopy(library)
    lib.fit(np.zeros((2, n_inputs)))
    return int(lib.n_output_features_)


# ---------------------------------------------------------------------- compilation
def compile_terms(library: BaseFeatureLibrary, n_inputs: int) -> list[Term]:
    """Structured terms of a *fitted* library, in its output-feature order."""
    if isinstance(library, ps.GeneralizedLibrary):
        if getattr(library, "tensor_array", None) is not None:
            raise ConfigError("library: tensored GeneralizedLibrary parts cannot be compiled")
        terms: list[Term] = []
        per = library.inputs_per_library
        for i, lib in enumerate(library.libraries_full_):
            if i in library.exclude_libraries:
                continue
            idx = list(dict.fromkeys(per[i])) if i < len(per) else list(range(n_inputs))
            terms += [tuple((idx[j], op, p) for j, op, p in t) for t in compile_terms(lib, len(idx))]
        return terms
    if isinstance(library, ConcatLibrary):
        return [t for lib in library.libraries for t in compile_terms(lib, n_inputs)]
    if isinstance(library, ps.PolynomialLibrary):
        combos = library._combinations(
            n_inputs, library.degree, library.include_interaction,
            library.interaction_only, library.include_bias,
        )
        return [tuple((int(j), "pow", 1.0) for j in combo) for combo in combos]
    if isinstance(library, ps.FourierLibrary):
        terms = []
        for i in range(library.n_frequencies):
            for j in range(n_inputs):
                if library.include_sin:
                    terms.append(((j, "sin", float(i + 1)),))
                if library.include_cos:
                    terms.append(((j, "cos", float(i + 1)),))
        return terms
    if isinstance(library, _TermLibrary):
        return library.terms_for(n_inputs)
    raise ConfigError(
        f"library: {type(library).__name__} cannot be compiled into a fast evaluator; use "
        "PolynomialLibrary, FourierLibrary, TrigLibrary, RationalLibrary or GeneralizedLibrary"
    )
