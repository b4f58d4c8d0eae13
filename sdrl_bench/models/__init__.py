"""Dynamics models s_{t+1} = f(s_t, c_t): sparse SINDy laws and a neural-network baseline.

- ``base``: the ``DynamicsModel`` protocol and ``load_model`` (a loader registry by kind; it
  imports no concrete model, so torch loads only when an NN is used).
- ``terms``: the one table of term operations (numpy, scalar and generated-source forms).
- ``libraries``: pysindy feature libraries composed for an env, compiled into terms.
- ``sindy``, ``snap``: the SINDy model and the snapping of exact laws' coefficients.
- ``fast``, ``blas``: the compiled one-state and batch evaluators a surrogate env steps with.
- ``nn``, ``mlp``, ``nn_io``: the NN baseline, its ``torch.nn.Module``, saving it as data.
"""
