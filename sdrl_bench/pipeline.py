"""collect -> fit -> fidelity, as one plain function over typed arguments (no Hydra, no MLflow).

``check`` validates a job cheaply (no env steps, no fit); ``fit_dynamics`` does the work and
returns a ``FitResult`` that ``tracking.log_fit`` records.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable

import numpy as np

from sdrl_bench import ConfigError, seeds
from sdrl_bench.data import PolicyFactory, Transitions, collect, held_out_test_set, load_csv, random_policy
from sdrl_bench.envs.base import EnvSpec
from sdrl_bench.fidelity import FidelityReport, evaluate, open_loop_episode
from sdrl_bench.models.libraries import LibraryPart, build_library, count_features
from sdrl_bench.models.base import DynamicsModel
from sdrl_bench.models.sindy import SindyModel


@dataclass(frozen=True)
class FitJob:
    """Everything one fit needs."""

    spec: EnvSpec
    """The environment."""
    library_parts: tuple[LibraryPart, ...]
    """Feature library parts (pysindy libraries and the inputs they act on)."""
    optimizer: Any
    """A pysindy optimizer (cloned for the fit)."""
    n_transitions: int = 75
    """Transitions to collect from the real env."""
    policy: PolicyFactory | None = None
    """Collector policy factory (None: uniform random)."""
    epsilon: float = 0.2
    """Probability of a uniform random action instead of the policy's."""
    max_steps_per_episode: int | None = None
    """Cut each collected episode after this many steps and start the next one (None: play
    each episode to its end or the env's limit)."""
    seed: int = 0
    """The run seed: the collection's reset seeds (``seeds``, purpose ``collect``; the
    exploration of each episode is seeded by its reset seed) and the fit's own seed."""
    dataset_path: str | None = None
    """A dataset CSV to fit instead of collecting."""
    exclude_bound_transitions: bool = True
    """Drop rows whose next state lies on a known bound from the fit (the surrogate applies
    the bounds itself)."""
    names: dict = field(default_factory=dict)
    """Human names of the choices (env, library, optimizer, collector) for tags."""
    surrogate: str = "sindy"
    """Kind of dynamics model: "sindy" (uses the library and optimizer) or another kind."""
    wrap_env: Callable | None = None
    """Wraps every real env the collection steps (the RL accounting counts steps with it)."""
    model_factory: Callable[..., DynamicsModel] | None = None
    """Builds the unfitted model: called as ``factory(library=, optimizer=, seed=)`` for SINDy
    and ``factory(seed=)`` otherwise. None: ``SindyModel``."""
    learn_events: bool = True
    """Learn the outcome model of every event the env declares from the same data
    (``surrogate.events``); False: the task's rules alone decide events."""
    min_events: int | None = None
    """Real events needed before an event model is fitted (None: each event's own ``min_events``)."""
    tuning_real_steps: int = 0
    """Real steps spent choosing the model's hyperparameters on real data other than the run's
    (``surrogate.tuning_real_steps``): counted as ``tuning`` by every run the model serves."""


@dataclass
class FitResult:
    job: FitJob
    data: Transitions
    dataset_hash: str
    n_fit_rows: int
    test_name: str
    test: Transitions
    test_hash: str
    model: DynamicsModel
    fidelity: FidelityReport
    episode_true: np.ndarray
    episode_pred: np.ndarray
    seconds: dict[str, float]
    events: dict = field(default_factory=dict)
    """{event name: its learned ``surrogate.events.EventModel`` or None}, from the same data."""
    spec: Any = None
    """The spec the fit's surrogate is built on: the job's, with the constants learned from the
    same data when ``own_data`` (``surrogate.own_data``); None: the job's."""
    learned: dict = field(default_factory=dict)
    """{prior key: value} of the constants learned from the fit's data (empty without ``own_data``)."""

    def __post_init__(self) -> None:
        if self.spec is None:
            self.spec = self.job.spec


def check(job: FitJob) -> tuple[Any, Transitions | None]:
    """Cheap validation before any env step or fit. Returns (library, loaded dataset or None)."""
    spec = job.spec
    threshold = getattr(job.optimizer, "threshold", getattr(getattr(job.optimizer, "opt", None), "threshold", 0.0))
    if threshold is not None and threshold < 0:
        raise ConfigError(f"optimizer.threshold must be >= 0, got {threshold}")
    library = build_library(job.library_parts, spec.target_names, spec.control_names)
    n_terms = 0
    if job.surrogate == "sindy":
        try:  # the library fitted on a few zero rows: a setting it refuses only when fitted (degree=-2)
            n_terms = count_features(library, len(spec.input_names))
        except ConfigError:
            raise
        except Exception as exc:  # noqa: BLE001 - the library's own message, in one line
            why = " ".join(str(exc).split()) or type(exc).__name__
            raise ConfigError(f"library ({job.names.get('library', 'library')}): {why}") from None
    model = build_model(job, library)  # model hyperparameters are validated in its __init__
    if hasattr(model, "check_inputs"):  # a per-equation library names its inputs: checked before any data
        model.check_inputs(spec.target_names, spec.control_names)
    data = load_csv(spec, job.dataset_path) if job.dataset_path else None
    n_rows = len(data) if data is not None else job.n_transitions
    if data is None and job.n_transitions <= 0:
        raise ConfigError(f"n_transitions must be positive, got {job.n_transitions}")
    if n_rows < n_terms:
        what = f"dataset.path has {n_rows} rows" if data is not None else f"n_transitions={n_rows}"
        raise ConfigError(
            f"{what}: fewer transitions than the {n_terms} terms of library "
            f"'{job.names.get('library', 'library')}' for env '{spec.name}'"
        )
    if not 0.0 <= job.epsilon <= 1.0:
        raise ConfigError(f"collector.epsilon must be in [0, 1], got {job.epsilon}")
    spec.check_task(job.seed)  # the task's functions on two real reset states, before any real step
    if data is None and hasattr(job.policy, "validate"):
        job.policy.validate(spec)  # e.g. an expert: checked now, trained only when collecting
    elif data is None and job.policy is not None:
        env = spec.make_env()
        try:
            job.policy(spec, env)  # a collector the env cannot serve fails here, not mid-run
        finally:
            env.close()
    return library, data


def fit_dynamics(job: FitJob, checked: tuple[Any, Transitions | None] | None = None) -> FitResult:
    """Collect (or load) transitions, fit SINDy, score it on the env's held-out test set.

    ``checked`` is what ``check(job)`` returned, when the caller validated the job already.
    """
    library, data = checked if checked is not None else check(job)
    spec = job.spec
    seconds: dict[str, float] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    if data is None:
        data = collect(spec, job.policy or random_policy, job.n_transitions, job.epsilon, seeds.reset_seed(job.seed, "collect"),
                       max_steps_per_episode=job.max_steps_per_episode, wrap_env=job.wrap_env)
    seconds["collect_wall"] = time.perf_counter() - t0
    seconds["collect_cpu"] = time.process_time() - c0
    return fit_transitions(job, library, data, seconds=seconds)


def fit_transitions(job: FitJob, library: Any, data: Transitions, test: tuple[str, Transitions] | None = None,
                    seconds: dict[str, float] | None = None) -> FitResult:
    """Fit the job's model on ``data`` (the rows of its regime, off the known bounds) and score
    it on the env's held-out test set (``test``: that set, when the caller holds it already).
    Dyna refits every round through here, on all the real data so far."""
    spec = job.spec
    seconds = dict(seconds or {})
    x, u = spec.model_inputs(data.states, data.actions)
    x_next = data.next_states[:, spec.target_index]
    keep = ~spec.at_bound(data.next_states) if job.exclude_bound_transitions else np.ones(len(data), bool)
    regime = spec.fit_rows(data.episode, data.states, data.rewards, data.next_states)
    if regime is not None:  # the regime the model describes (LunarLander: flight)
        keep &= regime
    if keep.sum() == 0:
        raise ConfigError("dataset: every transition lies on a state bound or outside the fitted regime; nothing to fit")
    model = build_model(job, library).fit(
        x[keep], u[keep], x_next[keep], state_names=spec.target_names, control_names=spec.control_names,
        bounds=spec.target_bounds(),
    )
    seconds["fit_wall"] = model.fit_wall_seconds_
    seconds["fit_cpu"] = model.fit_cpu_seconds_
    from sdrl_bench.surrogate.events import event_metrics, fit_events  # noqa: PLC0415
    from sdrl_bench.surrogate.own_data import learn_from_run  # noqa: PLC0415

    t0, c0 = time.perf_counter(), time.process_time()
    spec, learned = learn_from_run(spec, data, model, keep)  # the job's spec unless own_data
    events = fit_events(spec.task, data, job.min_events, seed=job.seed) if job.learn_events else {}
    seconds["events_wall"], seconds["events_cpu"] = time.perf_counter() - t0, time.process_time() - c0

    t0, c0 = time.perf_counter(), time.process_time()
    test_name, test = test if test is not None else held_out_test_set(spec)
    norm = {n: s["std"] for n, s in data.normalization(spec).items()}
    report = evaluate(model, spec, test, norm_std=norm, test_name=test_name)
    if spec.defines_task:  # reward, termination and derived-flag fidelity of the surrogate built on it
        from sdrl_bench.surrogate.fidelity import surrogate_fidelity  # noqa: PLC0415

        report.metrics.update(surrogate_fidelity(model, spec, test))
        report.metrics.update(event_metrics(spec.task, events, test))
    report.metrics.update({f"learned/{k}": v for k, v in learned.items() if np.isfinite(v)})
    ep_true, ep_pred = open_loop_episode(model, spec, test, int(test.episode[0]))
    seconds["evaluate_wall"] = time.perf_counter() - t0
    seconds["evaluate_cpu"] = time.process_time() - c0
    return FitResult(
        job=job, data=data, dataset_hash=data.content_hash(), n_fit_rows=int(keep.sum()),
        test_name=test_name, test=test, test_hash=test.content_hash(), model=model,
        fidelity=report, episode_true=ep_true, episode_pred=ep_pred, seconds=seconds, events=events,
        spec=spec, learned=learned,
    )


def build_model(job: FitJob, library: Any) -> DynamicsModel:
    """The unfitted dynamics model a job asks for."""
    if job.surrogate == "sindy":
        factory = job.model_factory or SindyModel
        return factory(library=library, optimizer=job.optimizer, seed=job.seed)
    if job.model_factory is None:
        raise ConfigError(f"surrogate.model: no model factory for surrogate kind {job.surrogate!r}")
    return job.model_factory(seed=job.seed)

