"""sdrl-bench: sparse-dynamics (SINDy) surrogate environments for reinforcement learning."""

__version__ = "0.1.0"


class ConfigError(ValueError):
    """Bad user input (a config key, a file): reported as one line, before expensive work."""


class Terminated(KeyboardInterrupt):
    """A stop signal (SIGTERM, SIGINT) raised as an exception in the main thread, so that open
    runs unwind and end KILLED (and Optuna fails the running trial, as it does on Ctrl-C)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def raise_on_stop_signals() -> None:
    """In the main thread: SIGTERM and SIGINT raise ``Terminated``."""
    import signal

    def handler(signum, frame):
        raise Terminated(signum)

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, handler)


def _register_envs() -> None:
    """Register ``sdrl/Surrogate-v0`` with gymnasium (lazily imported: ``sdrl_bench.surrogate.env``)."""
    import gymnasium

    if "sdrl/Surrogate-v0" not in gymnasium.registry:
        # No max_episode_steps: the surrogate truncates at its spec's limit itself.
        gymnasium.register(id="sdrl/Surrogate-v0", entry_point="sdrl_bench.surrogate.env:SurrogateEnv")


_register_envs()
