"""Dynamics models s_{t+1} = f(s_t, c_t): sparse SINDy laws and a neural-network baseline.

- ``base``: the ``DynamicsModel`` protocol and ``load_model`` (a loader registry by kind; it
  imports no concrete model, so torch loads only when an NN is used).
- ``terms``: the one table of term operations (numpy, scalar and generated-source forms).
- ``libraries``: pysindy feature libraries composed for an env, compiled into terms.
- ``per_equation``: per-equation libraries (own terms per state, YAML-defined) and their model.
- ``sindy``, ``snap``: the SINDy model and the snapping of exact laws' coefficients.
- ``fast``, ``blas``: the compiled one-state and batch evaluators a surrogate env steps with.
- ``nn``, ``mlp``, ``nn_io``: the NN baseline, its ``torch.nn.Module``, saving it as data.
"""

import importlib.util
import sys

from sdrl_bench.models.base import register_loader


def _skip_pysindy_sbr() -> None:
    """Where numpyro is not installed, mark ``pysindy.optimizers.sbr`` absent before pysindy loads.

    Why: pysindy's optimizers package tries to import its SBR optimizer, whose module imports jax
    and then numpyro; without numpyro that import fails and pysindy goes on without SBR. With the
    ``[jax]`` extra (jax, no numpyro) every process paid for loading jax first: 0.7-0.9 s of each
    ``import pysindy`` here (2.55-2.75 s against 1.80-1.87 s, measured with two jobs running).
    Marked absent, the import fails at once, with the same outcome: no SBR. With numpyro
    installed, nothing is changed."""
    if "pysindy" not in sys.modules and importlib.util.find_spec("numpyro") is None:
        sys.modules.setdefault("pysindy.optimizers.sbr", None)  # None: "import halted", an ImportError


_skip_pysindy_sbr()

# Loaded lazily by kind (the module imports pysindy only when a file of this kind is read).
register_loader("per_equation", "sdrl_bench.models.per_equation:PerEquationModel")
