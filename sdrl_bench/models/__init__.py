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

from sdrl_bench.models.base import register_loader

# Loaded lazily by kind (the module imports pysindy only when a file of this kind is read).
register_loader("per_equation", "sdrl_bench.models.per_equation:PerEquationModel")
