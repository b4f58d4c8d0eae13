"""Optuna search of the SINDy hyperparameters: space, study, storage, refinement, summary."""
