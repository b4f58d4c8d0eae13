"""sdrl-bench: sparse-dynamics (SINDy) surrogate environments for reinforcement learning."""

__version__ = "0.1.0"


class ConfigError(ValueError):
    """Bad user input (a config key, a file): reported as one line, before expensive work."""
