"""sdrl-bench: sparse-dynamics (SINDy) surrogate environments for reinforcement learning."""

__version__ = "0.1.0"


class ConfigError(ValueError):
    """Bad user input (a config key, a file): reported as one line, before expensive work."""


def _register_envs() -> None:
    """Register ``sdrl/Surrogate-v0`` with gymnasium (lazily imported: ``sdrl_bench.surrogate.env``)."""
    import gymnasium

    if "sdrl/Surrogate-v0" not in gymnasium.registry:
        # No max_episode_steps: the surrogate truncates at its spec's limit itself.
        gymnasium.register(id="sdrl/Surrogate-v0", entry_point="sdrl_bench.surrogate.env:SurrogateEnv")


_register_envs()
