"""A fit's data and model as MLflow knows them: the training transitions and the held-out test
set as dataset inputs (digests, contexts "training"/"testing"), and the surrogate as a logged
pyfunc model from code (``pyfunc_model.py``) with a signature and an input example."""

from __future__ import annotations

import contextlib
import json
import warnings
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from sdrl_bench.tracking.client import Run

CODE = Path(__file__).with_name("pyfunc_model.py")
TERMS_CODE = Path(__file__).with_name("terms_pyfunc.py")
NN_CODE = Path(__file__).with_name("nn_pyfunc.py")


@contextlib.contextmanager
def _fluent_target(uri: str, experiment_id: str) -> Iterator[None]:
    """MLflow's module-level tracking URI and experiment set to the run's, for the calls that
    read them (model logging creates the logged model in the "current" experiment)."""
    import os

    import mlflow

    previous = mlflow.get_tracking_uri() if mlflow.tracking._tracking_service.utils.is_tracking_uri_set() else None
    prev_exp = os.environ.get("MLFLOW_EXPERIMENT_ID")
    mlflow.set_tracking_uri(uri)
    os.environ["MLFLOW_EXPERIMENT_ID"] = experiment_id
    try:
        yield
    finally:
        mlflow.set_tracking_uri(previous)
        if prev_exp is None:
            os.environ.pop("MLFLOW_EXPERIMENT_ID", None)
        else:
            os.environ["MLFLOW_EXPERIMENT_ID"] = prev_exp


def _frame(transitions, spec):
    from sdrl_bench.data import columns

    df = transitions.to_frame(spec)
    return df[columns(spec)]


def _csv_source(run: Run, artifact: str):
    """Where the training CSV can be fetched: the run's artifact (a server's ``get-artifact``
    URL when artifacts are proxied by an ``mlflow server``)."""
    from urllib.parse import quote

    from mlflow.data.http_dataset_source import HTTPDatasetSource

    from sdrl_bench.tracking.client import mlflow_client
    from sdrl_bench.tracking.meta import without_credentials

    base = mlflow_client(run.uri).get_run(run.run_id).info.artifact_uri.rstrip("/")
    if base.startswith("mlflow-artifacts:") and run.uri.startswith(("http://", "https://")):
        server = without_credentials(run.uri).rstrip("/")  # a dataset's source is shown to whoever reads the run
        return HTTPDatasetSource(f"{server}/get-artifact?path={quote(artifact, safe='')}&run_uuid={run.run_id}")
    return f"{base}/{artifact}"


def log_datasets(run: Run, result, csv_artifact: str, rows=None) -> None:
    """The training transitions (source: this run's CSV artifact, under a name of this run's) and the held-out test set
    (source: the code that generates it) as the run's dataset inputs, with MLflow's digests.
    ``rows``: the transitions the CSV holds instead of all of ``result.data`` (context
    "training-new-rows": a Dyna round's additions)."""
    import mlflow.data
    from mlflow.data.code_dataset_source import CodeDatasetSource
    from mlflow.entities import DatasetInput, InputTag
    from mlflow.utils.mlflow_tags import MLFLOW_DATASET_CONTEXT


    spec = result.job.spec
    test_source = CodeDatasetSource({"sdrl.test_set": result.test_name, "sdrl.test_set_sha256": result.test_hash,
                                     "generator": "sdrl_bench.data.held_out_test_set"})
    inputs = []
    # named for this run: MLflow reuses a dataset of the same name and digest, and a dataset of
    # another run's name would point at that run's file (gone when that run is deleted)
    train = (result.data, f"{spec.name}-transitions-{run.run_id[:8]}", "training") if rows is None else \
        (rows, f"{spec.name}-new-transitions-{run.run_id[:8]}", "training-new-rows")
    for data, name, context, src in ((*train, _csv_source(run, csv_artifact)),
                                     (result.test, result.test_name, "testing", test_source)):
        with warnings.catch_warnings():  # MLflow's hints on source ambiguity and integer columns
            warnings.simplefilter("ignore", UserWarning)
            ds = mlflow.data.from_pandas(_frame(data, spec), source=src, name=name)
            inputs.append(DatasetInput(ds._to_mlflow_entity(), tags=[InputTag(MLFLOW_DATASET_CONTEXT, context)]))
    log_inputs_retrying(run, inputs)


def log_priors(run: Run, priors) -> None:
    """The env's declared priors (``envs.task.Prior``) as the run's dataset inputs (context
    "prior"): name, kind, what each sets, its source and the real steps behind it, with a digest
    of the declaration, so a run names every prior its surrogate rests on."""
    import hashlib
    from dataclasses import asdict

    from mlflow.data.code_dataset_source import CodeDatasetSource
    from mlflow.data.meta_dataset import MetaDataset
    from mlflow.entities import DatasetInput, InputTag
    from mlflow.utils.mlflow_tags import MLFLOW_DATASET_CONTEXT

    inputs = []
    for p in priors:
        record = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(p).items()}
        digest = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]
        source = CodeDatasetSource({k: str(v) for k, v in record.items() if v not in (None, 0, "")})
        ds = MetaDataset(source, name=p.name, digest=digest)
        inputs.append(DatasetInput(ds._to_mlflow_entity(), tags=[InputTag(MLFLOW_DATASET_CONTEXT, f"prior:{p.kind}")]))
    if inputs:
        log_inputs_retrying(run, inputs)


def log_inputs_retrying(run: Run, inputs: list, attempts: int = 5) -> None:
    """``log_inputs``, retried when it loses a race. MLflow's SQL store looks for an existing
    dataset (same name and digest), then inserts one: two processes logging the same dataset at
    once (a sweep's parallel jobs share the held-out test set) can both insert, and the second
    fails its UNIQUE constraint (a parallel sweep in CI lost a job to it once). Its transaction
    is rolled back whole, so a retry finds the first one's row and links to it."""
    import time

    from mlflow.exceptions import MlflowException

    from sdrl_bench.tracking.client import mlflow_client

    for attempt in range(attempts):
        try:
            mlflow_client(run.uri).log_inputs(run.run_id, datasets=inputs)
            return
        except MlflowException as exc:
            if attempt == attempts - 1 or not any(s in str(exc) for s in ("UNIQUE constraint", "IntegrityError")):
                raise
            time.sleep(0.05 * (attempt + 1))


def terms_table(model) -> dict | None:
    """A model with structured terms (SINDy, per-equation) as the data ``terms_pyfunc`` evaluates:
    input and output names, terms, coefficients, stages; None for other models."""
    import numpy as np

    terms, coef = getattr(model, "terms_", None), getattr(model, "coef_", None)
    if terms is None or coef is None:
        return None
    return {"format": "sdrl-bench/terms-v1", "inputs": list(model.state_names_) + list(model.control_names_),
            "outputs": list(model.state_names_), "terms": [[[int(j), str(op), float(p)] for j, op, p in t] for t in terms],
            "coef": np.asarray(coef, dtype=float).tolist(), "stages": getattr(model, "stages_", None)}


def model_io_example(result, n: int = 5):
    """(input example, next-state predictions) on the first ``n`` held-out transitions: the
    model's inputs by name (regressed states, then controls) and its prediction."""
    import pandas as pd

    spec, model = result.job.spec, result.model
    x, u = spec.model_inputs(result.test.states[:n], result.test.actions[:n])
    example = pd.DataFrame(np.concatenate([x, u], axis=1), columns=list(spec.input_names))
    pred = model.predict(x, u)
    return example, pd.DataFrame(pred, columns=[f"{s}_next" for s in spec.target_names])


def log_surrogate_model(run: Run, result) -> str:
    """Log the fitted dynamics model as the run's MLflow model, named ``<env>-<library>-<kind>``
    and described by its equations; returns its model URI (``models:/<model id>``).

    A model with structured terms (SINDy) is logged self-contained (``terms_pyfunc.py`` and
    ``terms.json``): it loads with ``mlflow`` and ``numpy`` alone. An NN (MLP or probabilistic
    ensemble) is too (``nn_pyfunc.py``, its ``model.json`` and weights): ``mlflow``, ``numpy`` and
    ``torch``. Any other model is logged with the harness's loader (``pyfunc_model.py``). All
    predict the next regressed states from the model's inputs by name."""
    import mlflow
    from mlflow.models import Model, infer_signature

    from sdrl_bench.tracking.client import mlflow_client

    spec, model = result.job.spec, result.model
    example, output = model_io_example(result)
    table = terms_table(model)
    library = result.job.names.get("library", "model") if result.job.surrogate == "sindy" else result.job.surrogate
    name = f"{spec.name}-{library}-{model.kind}"
    with tempfile.TemporaryDirectory() as tmp:
        if table is not None:
            code, requirements = TERMS_CODE, [f"mlflow=={mlflow.__version__}", f"numpy=={np.__version__}"]
            path = Path(tmp) / "terms.json"
            path.write_text(json.dumps(table))
            artifacts = {"terms": str(path)}
        else:
            model_dir = Path(tmp) / "model"
            model.save(model_dir / "model.json")
            artifacts = {"model": str(model_dir)}
            from sdrl_bench.models.nn_io import FORMAT as NN_FORMAT  # torch: an NN's file format

            if json.loads((model_dir / "model.json").read_text()).get("format") == NN_FORMAT:
                import torch

                code, requirements = NN_CODE, [f"mlflow=={mlflow.__version__}", f"numpy=={np.__version__}",
                                               f"torch=={torch.__version__.split('+')[0]}"]
            else:
                code, requirements = CODE, [f"mlflow=={mlflow.__version__}", "sdrl-bench"]
        exp_id = mlflow_client(run.uri).get_run(run.run_id).info.experiment_id
        with _fluent_target(run.uri, exp_id), warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # MLflow's integer-column hints
            info = Model.log(
                artifact_path=None, name=name, flavor=mlflow.pyfunc, run_id=run.run_id,
                python_model=str(code), artifacts=artifacts,
                signature=infer_signature(example, output), input_example=example,
                pip_requirements=requirements,
                tags={"sdrl.env": spec.name, "sdrl.surrogate": result.job.surrogate, "sdrl.library": library},
            )
    with contextlib.suppress(Exception):  # a store without logged-model tags keeps the model undescribed
        mlflow_client(run.uri).set_logged_model_tags(
            info.model_id, {"mlflow.note.content": f"Next {', '.join(spec.target_names)} from "
                            f"{', '.join(spec.input_names)}:\n\n```\n{model.describe().strip()}\n```\n"})
    return info.model_uri
