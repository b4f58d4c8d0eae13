"""The command line checked before Hydra runs: one line per mistake, exit 2, nothing written.

Hydra reports a bad override, an unknown key or group option, or a YAML syntax error in a config
file as several lines (and exits 1), after it has made its output folder. The entry points call
``check_command_line`` first: it parses the overrides with Hydra's own grammar, composes the
config once with Hydra's compose API (the package's configs, ``--config-dir``, every override;
a sweep ``a=1,2`` is checked with each of its values), and turns what fails into one line that
names the key or the file, with the nearest valid name. Hand-written because Hydra exposes no
hook between composition and its error report; the composition itself is Hydra's.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Sequence
from pathlib import Path

from sdrl_bench import ConfigError

_YAML_WHERE = re.compile(r'in "([^"]+)", line (\d+), column (\d+)')
SEARCH_EXPORTS = "mlruns/search"
"""Where a search writes its best config by default (``study.export_dir`` of conf/search_app.yaml,
less ``/experiment``): an unknown ``experiment=<name>`` found there gets the search path's hint."""


def _parse(overrides: Sequence[str]):
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    parser = OverridesParser.create()
    out = []
    for text in overrides:
        try:
            out.extend(parser.parse_overrides([text]))
        except OverrideParseException as exc:
            why = str(exc).splitlines()[0]
            raise ConfigError(f"{text}: cannot parse this override ({why}); see "
                              "https://hydra.cc/docs/advanced/override_grammar/basic") from None
    return out


def _variants(parsed) -> list[list[str]]:
    """Override lists to compose: each sweep's values in turn (the others at their first value)."""
    base = []
    sweeps: list[tuple[int, list[str]]] = []
    for i, o in enumerate(parsed):
        prefix = {"ADD": "+", "FORCE_ADD": "++", "DEL": "~"}.get(o.type.name, "")
        if o.is_sweep_override():
            values = list(o.sweep_string_iterator())
            base.append(f"{prefix}{o.key_or_group}={values[0]}")
            sweeps.append((i, [f"{prefix}{o.key_or_group}={v}" for v in values]))
        else:
            base.append(o.input_line)
    variants = [base]
    for i, alts in sweeps:
        for alt in alts[1:]:
            variants.append(base[:i] + [alt] + base[i + 1:])
    return variants


def _keys(node, prefix: str = "") -> list[str]:
    from omegaconf import DictConfig

    out = []
    if isinstance(node, DictConfig):
        for k in node.keys():
            full = f"{prefix}.{k}" if prefix else str(k)
            out.append(full)
            try:
                child = node._get_node(k)
            except Exception:  # an unresolvable interpolation: its key still counts
                continue
            out += _keys(child, full)
    return out


def _one_line(exc: BaseException, overrides: Sequence[str], compose) -> str:
    text = str(exc)
    first = text.splitlines()[0] if text else type(exc).__name__
    where = _YAML_WHERE.findall(text)
    if where or type(exc).__module__.startswith("yaml"):
        file, line, _ = where[-1] if where else ("?", "?", "?")
        problem = getattr(exc, "problem", None) or first
        return f"{file}:{line}: YAML syntax error: {problem}"
    missing = re.match(r"In '[^']*': Could not find '([^']+)/([^']+)'", first) or re.match(r"Could not find '([^']+)/([^']+)'", first)
    if missing:
        group, option = missing.groups()
        options = re.findall(r"^\t(\S+)$", text, flags=re.M)
        near = difflib.get_close_matches(option, options, n=1)
        hint = f"; did you mean {group}={near[0]}?" if near else ""
        searched = Path(SEARCH_EXPORTS) / group / f"{option}.yaml"
        if group == "experiment" and searched.is_file():  # a search's best config, its folder not on the search path
            hint = f"; a search wrote {searched}: add 'hydra.searchpath=[file://{SEARCH_EXPORTS}]'"
        return f"{group}={option}: no such option of '{group}' (options: {', '.join(options)}){hint}"
    cause = exc.__cause__
    if type(cause).__name__ == "ValidationError" and getattr(cause, "full_key", None):  # OmegaConf refused the value
        return f"{cause.full_key}: {str(getattr(cause, 'msg', cause)).splitlines()[0]}"  # (Hydra's line names no reason)
    unknown = re.search(r"full_key: (\S+)", text) or re.match(r"Could not override '([^']+)'", first)
    if unknown:
        key = unknown.group(1)
        ok = [o for o in overrides if not o.lstrip("+~").startswith(key.split(".")[0] + ".") and
              not o.lstrip("+~").startswith(key + "=")]
        try:
            known = [k for k in _keys(compose(ok)) if not k.rsplit(".", 1)[-1].startswith("_")]  # not _target_
        except Exception:
            known = []
        return f"{key}: unknown config key{_key_hint(key, known)} (to add a new key: +{key}=...)"
    return " ".join(text.split())


def _key_hint(key: str, known: Sequence[str]) -> str:
    """The nearest known key: among the keys of the same block when that block exists (its keys
    listed when none is near: ``optimizer=sr3`` has no ``alpha``), else among all keys
    (``n_trials`` -> ``search.n_trials``)."""
    parent, _, leaf = key.rpartition(".")
    siblings = sorted(k.rsplit(".", 1)[-1] for k in known if k.rpartition(".")[0] == parent) if parent else []
    if siblings:
        near = difflib.get_close_matches(leaf, siblings, n=1)
        shown = ", ".join(siblings[:12]) + (f", ... ({len(siblings)} keys)" if len(siblings) > 12 else "")
        return f"; did you mean {parent}.{near[0]}?" if near else f"; {parent} has {shown}"
    near = difflib.get_close_matches(key, known, n=1)
    return f"; did you mean {near[0]}?" if near else ""


def check_command_line(argv: Sequence[str], config_name: str, check_job: Callable | str | None = None) -> None:
    """Raise a one-line ``ConfigError`` for what Hydra would reject in ``argv`` (see the module
    docstring); return quietly when Hydra only prints help or info. For a ``-m`` sweep,
    ``check_job`` (a callable or ``"module:name"``, given each job's composed config and
    overrides) runs too: a job's own check before the sweep's parent run exists."""
    from hydra import compose, initialize_config_module
    from hydra._internal.utils import get_args_parser
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    try:
        args, _ = get_args_parser().parse_known_args(list(argv))
    except SystemExit:
        return  # argparse's own message (a bad flag): Hydra reports it
    if args.help or args.hydra_help or args.info or args.cfg or args.shell_completion or args.config_path:
        return
    name = args.config_name or config_name
    parsed = _parse(args.overrides)
    if args.config_dir and not Path(args.config_dir).is_dir():
        raise ConfigError(f"--config-dir: {args.config_dir} is not a folder")
    search = [f"file://{Path(args.config_dir).resolve()}"] if args.config_dir else []

    def with_searchpath(overrides: Sequence[str]) -> list[str]:
        """``overrides`` with the --config-dir on the search path, beside any ``hydra.searchpath``
        the command line sets (Hydra searches both)."""
        if not search:
            return list(overrides)
        given = [o for o in overrides if o.startswith("hydra.searchpath=")]
        paths = [str(p) for o in given for p in (_parse([o])[0].value() or [])]
        quoted = ",".join("'" + p.replace("\\", "\\\\").replace("'", "\\'") + "'" for p in [*paths, *search])
        return [o for o in overrides if o not in given] + [f"hydra.searchpath=[{quoted}]"]

    def composed(overrides: Sequence[str]):
        GlobalHydra.instance().clear()
        with initialize_config_module(config_module="sdrl_bench.conf", version_base="1.3"):
            return compose(config_name=name, overrides=with_searchpath(overrides))

    uris, storages, jobs = [], [], []
    try:
        for overrides in _variants(parsed):
            cfg = composed(overrides)
            resolved = _resolve(cfg)
            uris.append(_select(cfg, "tracking.uri", None))
            _check_experiment(_select(cfg, "tracking.experiment", ""))
            if OmegaConf.select(cfg, "study", default=None) is not None:  # sdrl-bench-search
                storages.append(_select(cfg, "study.storage", None))
            if resolved:  # a job whose config reads ${hydra:...} is checked by the job itself
                jobs.append((cfg, with_searchpath(overrides)))
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(_one_line(exc, _variants(parsed)[0], composed)) from None
    finally:
        GlobalHydra.instance().clear()
    _check_stores([u for u in uris if u is not _LATER], [u for u in storages if u is not _LATER])
    if args.multirun:
        _check_launcher(with_searchpath(_variants(parsed)[0]), name)
    if args.multirun and check_job is not None:
        _check_jobs(check_job, jobs)


def _check_launcher(overrides: Sequence[str], name: str) -> None:
    """The sweep's launcher settings (Hydra's joblib launcher, ``hydra.launcher.*``) that joblib
    would refuse with a traceback after the sweep's parent run exists: ``n_jobs`` must be a
    whole number other than 0 (joblib: -1 is every core, -2 all but one)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    from sdrl_bench.cli.args import n_jobs_problem

    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="sdrl_bench.conf", version_base="1.3"):
            cfg = compose(config_name=name, overrides=list(overrides), return_hydra_config=True)
        n_jobs = OmegaConf.select(cfg, "hydra.launcher.n_jobs", default=None)
    except Exception:  # noqa: BLE001  (another launcher's config, a value only the app resolves: Hydra's to report)
        return
    finally:
        GlobalHydra.instance().clear()
    problem = None if n_jobs is None else n_jobs_problem(n_jobs)
    if problem:
        raise ConfigError(f"hydra.launcher.n_jobs: {problem}")


def _check_jobs(check_job: Callable | str, jobs) -> None:
    """``check_job`` on each (config, overrides): its ConfigError stops the sweep; anything else
    is what only the running app can tell, and the job's own check reports it."""
    import importlib

    if isinstance(check_job, str):
        module, _, name = check_job.partition(":")
        check_job = getattr(importlib.import_module(module), name)
    for cfg, overrides in jobs:
        try:
            check_job(cfg, overrides)
        except ConfigError:
            raise
        except Exception:  # noqa: BLE001, S112
            continue


def _check_experiment(experiment) -> None:
    if experiment is not _LATER and (not isinstance(experiment, str) or not experiment.strip()):
        raise ConfigError(f"tracking.experiment: an experiment name is required, got {experiment!r}")


_LATER = object()
"""A value that resolves inside the running app only (``${hydra:...}``): checked by the job."""


def _select(cfg, key: str, default):
    from omegaconf import OmegaConf
    from omegaconf.errors import InterpolationResolutionError

    try:
        return OmegaConf.select(cfg, key, default=default)
    except InterpolationResolutionError:
        return _LATER


def _resolve(cfg) -> bool:
    """Every interpolation of ``cfg`` resolved once: a key that is missing is one line naming the
    key that refers to it (Hydra would print a traceback when the job reads it). Those of Hydra's
    own resolvers (``${hydra:...}``) resolve inside the running app only, and are left to it:
    False when the config has one."""
    from omegaconf import OmegaConf
    from omegaconf.errors import InterpolationResolutionError

    try:
        OmegaConf.to_container(cfg, resolve=True)
    except InterpolationResolutionError as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "hydra" in text.lower():
            return False
        raise ConfigError(f"{getattr(exc, 'full_key', None) or '?'}: {text}") from None
    return True


def _check_stores(uris, storages=()) -> None:
    """``tracking.uri`` and a search's ``study.storage`` must be strings, and each store is
    checked (``tracking.check_store``: a local SQLite file read-only, in milliseconds; a
    tracking server asked once for its health), so that a damaged, misplaced or unreachable one
    is named in about a second, not after the job's imports and validation (9-11 s for an RL
    experiment, 8-12 s for a search, measured) or MLflow's minutes of retries."""
    from sdrl_bench import tracking
    from sdrl_bench.search.location import resolve_storage

    for key, values, forms in (("tracking.uri", uris, "sqlite:///<file> or http://<host>:<port>"),
                               ("study.storage", storages, "sqlite:///<file>, an SQLAlchemy URL or journal:<file>")):
        for u in values:
            if u is not None and not isinstance(u, str):
                raise ConfigError(f"{key}: a URI is required ({forms}), got {u!r}")
    given = {tracking.resolve_uri(u): tracking.uri_key(u) for u in uris}
    mlflow_uris = list(given)
    for uri, key in given.items():
        tracking.check_store(uri, key, reach=True)
    for url in dict.fromkeys(resolve_storage(u) for u in storages):
        if url in mlflow_uris:
            raise ConfigError(f"study.storage: {url} is the MLflow store (tracking.uri); give the study its own file")
        tracking.check_store(url, key="study.storage", kind="optuna")


def unread_primary(argv: Sequence[str], config_name: str) -> str | None:
    """A line for a ``--config-dir`` that holds a file named as the package's primary config
    (``config.yaml``) while ``--config-name`` is not given: Hydra reads the package's, which comes
    first on its search path, and the user's file is silently passed over. None otherwise."""
    from hydra._internal.utils import get_args_parser

    try:
        args, _ = get_args_parser().parse_known_args(list(argv))
    except SystemExit:
        return None
    shadowed = Path(args.config_dir) / f"{config_name}.yaml" if args.config_dir and not args.config_name else None
    if shadowed is None or not shadowed.is_file():
        return None
    return (f"--config-dir: {shadowed} is not read (the package's {config_name}.yaml comes first); to use it, "
            f"rename it and pass --config-name <its name>, its defaults list starting with '{config_name}'")


def run_checked(app, config_name: str, prog: str, check_job: Callable | str | None = None) -> None:
    """An entry point: the command line checked first (``check_command_line``: one line on
    stderr and exit 2 for a bad override, key, group option, YAML file or damaged store, and for
    a sweep a bad job), then the Hydra ``app``: a callable, or ``"module:name"``, imported only
    after the check."""
    import importlib
    import sys

    try:
        unread = unread_primary(sys.argv[1:], config_name)
        if unread:
            print(f"{prog}: warning: {unread}", file=sys.stderr)
        check_command_line(sys.argv[1:], config_name, check_job)
    except ConfigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        sys.exit(2)
    if isinstance(app, str):
        module, _, name = app.partition(":")
        app = getattr(importlib.import_module(module), name)
    app()


def search_main() -> None:
    """Entry point of ``sdrl-bench-search``. It lives here, not in ``cli.search``, because that
    module imports pysindy, sklearn and optuna when it loads (about 4 s here), and an entry
    point's module loads before its function runs: here a bad command line is answered first."""
    run_checked("sdrl_bench.cli.search:app", "search_app", "sdrl-bench-search", check_job="sdrl_bench.cli.search:check_job")
