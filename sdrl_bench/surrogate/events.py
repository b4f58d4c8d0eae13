"""Learned events: what follows an env's declared events, learned from the run's own transitions.

An env declares its events as data (``envs.task.Event``: a trigger, outcomes, features, an
optional prior rule). This module, which knows no env, does the rest:

* ``label_events``: the real events in a dataset (rows where the trigger fires; each episode's
  first, unless declared otherwise) and the outcome each was seen to have (the first outcome
  whose termination window and reward match the record; the default when the episode went on
  through the window; unknown, and left out, when the record stops before the window ends);
* ``fit_event_model``: P(outcome | features) on the events the prior leaves open (or all), by
  scikit-learn's ``LogisticRegression`` on standardized features (L2, C=1; multinomial beyond two
  outcomes), with a cross-validated accuracy when the data allow; None below the event's
  ``min_events`` or with one outcome only (the task's own rules then decide alone);
* ``score_events``: the run's event predictor (the prior where it decides, else the learned
  model, else the default outcome) on held-out real events: accuracy, log loss, counts;
* ``EventModel.draw``: the surrogate's draw of an outcome per triggered row (``model_env``);
  ``logistic_numbers``, ``outcome_probabilities`` and ``draw_outcomes``: the same on numpy or jax
  arrays with given uniforms (``jax_step``).

A dynamics model fitted on one regime says nothing about what happens at such an event; a Dyna
loop brings back the agent's own events, and the surrogate then ends them as the real env did
with the learned probability. Nothing here is hand-written but the bookkeeping.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sdrl_bench.envs.functional import array_namespace
from sdrl_bench.envs.task import Event, Task


@dataclass
class EventData:
    """The real events of a dataset."""

    rows: np.ndarray
    """Row index (in the dataset) of each event's trigger."""
    pre: np.ndarray
    """Pre-event states (K, n_state)."""
    outcome: np.ndarray
    """Observed outcome index per event (K,)."""
    prior: np.ndarray
    """The prior's outcome index per event (K,); 0 everywhere without a prior."""

    def __len__(self) -> int:
        return len(self.rows)

    def subset(self, mask: np.ndarray) -> EventData:
        return EventData(self.rows[mask], self.pre[mask], self.outcome[mask], self.prior[mask])


def label_events(event: Event, data: Any) -> EventData:
    """The events of ``data`` (a ``data.Transitions``, rows in episode order) and their outcomes."""
    n_state = data.states.shape[1] if data.states.ndim == 2 else 0
    if not len(data):
        return EventData(np.zeros(0, int), np.zeros((0, n_state)), np.zeros(0, int), np.zeros(0, int))
    trig = np.asarray(event.trigger(data.states, data.actions, data.next_states), dtype=bool)
    ended = np.asarray(data.terminated, bool) | np.asarray(data.truncated, bool)
    ep = np.asarray(data.episode)
    starts = np.flatnonzero(np.r_[True, ep[1:] != ep[:-1]])
    window = event.window
    rows, labels = [], []
    for a, b in zip(starts, np.r_[starts[1:], len(ep)], strict=True):
        hits = np.flatnonzero(trig[a:b]) + a
        for i in hits[:1] if event.once_per_episode else hits:
            stop = np.flatnonzero(ended[i:min(i + window, b)])
            if len(stop):
                j = i + stop[0]
                if not data.terminated[j]:
                    continue  # truncated before an outcome could be seen
                label = 0
                for k, o in enumerate(event.outcomes):
                    if k and o.within is not None and j - i < o.within and (
                            o.observed_reward is None or data.rewards[j] == o.observed_reward):
                        label = k
                        break
            elif b - i >= window:
                label = 0  # went on through the window
            else:
                continue  # the record stops before the window ends: unknown
            rows.append(i), labels.append(label)
    idx = np.asarray(rows, dtype=int)
    pre = np.asarray(data.states, dtype=float)[idx] if len(idx) else np.zeros((0, n_state))
    prior = np.asarray(event.prior(pre), dtype=int) if event.prior is not None and len(idx) else np.zeros(len(idx), int)
    return EventData(idx, pre, np.asarray(labels, dtype=int), prior)


@dataclass
class EventModel:
    """P(outcome | pre-event features) of one event, fitted on real events."""

    event: str
    outcome_names: tuple[str, ...]
    feature_names: tuple[str, ...]
    classifier: Any
    """A fitted scikit-learn pipeline (scaler + logistic regression)."""
    n_events: int
    counts: dict[str, int]
    train_accuracy: float
    train_log_loss: float
    cv_accuracy: float = float("nan")
    """Accuracy of the same fit under stratified k-fold cross-validation on these events (nan
    when an outcome has fewer than 2 events)."""
    extra: dict = field(default_factory=dict)

    def probabilities(self, features: np.ndarray) -> np.ndarray:
        """(N, n_outcomes) outcome probabilities (0 for outcomes never seen in training)."""
        x = np.asarray(features, dtype=float)
        out = np.zeros((len(x), len(self.outcome_names)))
        if len(x):
            out[:, self.classifier.classes_] = self.classifier.predict_proba(x)
        return out

    def draw(self, features: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """An outcome index per row, drawn from ``probabilities`` with one uniform per row."""
        p = self.probabilities(features)
        return draw_outcomes(p, rng.random(len(p)))

    def metrics(self) -> dict[str, float]:
        return {"n_events": float(self.n_events), **{f"n_{k}": float(v) for k, v in self.counts.items()},
                "train_accuracy": self.train_accuracy, "train_log_loss": self.train_log_loss,
                "cv_accuracy": self.cv_accuracy}

    def to_dict(self) -> dict[str, Any]:
        """The fitted model as plain numbers (logged beside each fit)."""
        scaler, logit = self.classifier[0], self.classifier[-1]
        return {"kind": "logistic", "event": self.event, "outcomes": list(self.outcome_names),
                "classes": [int(c) for c in self.classifier.classes_], "features": list(self.feature_names),
                "mean": scaler.mean_.tolist(), "scale": scaler.scale_.tolist(), "coef": logit.coef_.tolist(),
                "intercept": logit.intercept_.tolist(), **self.metrics()}


def draw_outcomes(p: Any, u: Any) -> Any:
    """(N,) outcome indices for probabilities ``p`` (N, n_outcomes) and uniforms ``u`` (N,) in
    [0, 1): the first outcome whose cumulative probability exceeds u (``EventModel.draw``'s rule;
    numpy or jax arrays)."""
    xp = array_namespace(p, u)
    return xp.minimum((u[:, None] >= xp.cumsum(p, axis=1)[:, :-1]).sum(axis=1), p.shape[1] - 1)


def logistic_numbers(model: EventModel) -> tuple[np.ndarray, ...] | None:
    """(mean, scale, coef, intercept, classes) of a model whose classifier is a fitted
    standard scaler + logistic regression (what ``fit_event_model`` makes), as float arrays
    (classes: int); None for any other classifier. ``outcome_probabilities`` evaluates them."""
    steps = getattr(model.classifier, "steps", None)
    if not steps or len(steps) != 2:
        return None
    scaler, logit = steps[0][1], steps[1][1]
    if not all(hasattr(scaler, a) for a in ("mean_", "scale_")) or not all(
            hasattr(logit, a) for a in ("coef_", "intercept_", "classes_", "predict_proba")):
        return None
    coef = np.asarray(logit.coef_, dtype=float)
    n_features = coef.shape[1]
    mean = np.zeros(n_features) if scaler.mean_ is None else np.asarray(scaler.mean_, dtype=float)
    scale = np.ones(n_features) if scaler.scale_ is None else np.asarray(scaler.scale_, dtype=float)
    return mean, scale, coef, np.asarray(logit.intercept_, dtype=float), np.asarray(logit.classes_, dtype=int)


def outcome_probabilities(numbers: tuple, features: Any, n_outcomes: int) -> Any:
    """(N, n_outcomes) ``EventModel.probabilities`` from ``logistic_numbers``, as scikit-learn
    computes them (standardize; two classes: [1 - sigmoid, sigmoid] of the decision; more: its
    softmax), 0 for outcomes never seen in training; numpy or jax arrays (equal to rounding; jax
    in float64 once ``models.jax_eval.jax_modules`` turned it on, as ``jax_step`` does)."""
    mean, scale, coef, intercept, classes = numbers
    xp = array_namespace(features)
    x = (xp.asarray(features, dtype=xp.float64) - mean) / scale
    d = x @ coef.T + intercept
    if len(classes) <= 2:
        with np.errstate(over="ignore"):  # exp(-d) = inf far on the first class's side: p1 = 0
            p1 = 1.0 / (1.0 + xp.exp(-d[:, 0]))
        p = xp.stack([1.0 - p1, p1], axis=1)
    else:
        e = xp.exp(d - xp.max(d, axis=1, keepdims=True))
        p = e / xp.sum(e, axis=1, keepdims=True)
    col = {int(c): j for j, c in enumerate(classes)}
    zero = xp.zeros(x.shape[0])
    return xp.stack([p[:, col[k]] if k in col else zero for k in range(n_outcomes)], axis=1)


def _training_set(event: Event, events: EventData) -> EventData:
    if event.prior is not None and event.learn_on == "open":
        return events.subset(events.prior == 0)
    return events


def fit_event_model(event: Event, data: Any, min_events: int | None = None, c: float = 1.0,
                    seed: int = 0) -> EventModel | None:
    """The outcome model of ``event`` fitted on the events of ``data``, or None (fewer than
    ``min_events`` training events, default the event's own, or one outcome only)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.metrics import log_loss
    from sklearn.model_selection import StratifiedKFold, cross_val_score
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    train = _training_set(event, label_events(event, data))
    need = event.min_events if min_events is None else min_events
    if len(train) < need or len(np.unique(train.outcome)) < 2:
        return None
    x, y = np.asarray(event.features(train.pre), dtype=float), train.outcome

    def make():
        return make_pipeline(StandardScaler(), LogisticRegression(C=c, max_iter=1000))

    clf = make().fit(x, y)
    p = clf.predict_proba(x)
    smallest = int(min(np.bincount(y)[np.unique(y)]))
    cv = float("nan")
    if smallest >= 2:
        folds = StratifiedKFold(n_splits=int(min(5, smallest)), shuffle=True, random_state=seed)
        cv = float(np.mean(cross_val_score(make(), x, y, cv=folds, scoring="accuracy")))
    counts = {name: int(np.sum(y == k)) for k, name in enumerate(event.outcome_names)}
    return EventModel(event.name, event.outcome_names, event.feature_names, clf, len(y), counts,
                      float(np.mean(clf.classes_[p.argmax(axis=1)] == y)),
                      float(log_loss(y, p, labels=clf.classes_)), cv)


def predict_outcomes(event: Event, model: EventModel | None, events: EventData) -> np.ndarray:
    """The run's event predictor: the prior where it decides (an outcome other than the
    default), else the learned model's most probable outcome, else the default."""
    pred = events.prior.copy()
    open_ = pred == 0 if event.learn_on == "open" else np.ones(len(pred), bool)
    if model is not None and open_.any():
        pred[open_] = model.probabilities(event.features(events.pre[open_])).argmax(axis=1)
    return pred


def score_events(event: Event, model: EventModel | None, data: Any) -> dict[str, float]:
    """The event predictor on the real events of ``data`` (held out from the fit): accuracy of
    the run's predictor and of the prior alone, the learned model's log loss on the events it
    decides, counts per observed outcome."""
    from sklearn.metrics import log_loss

    events = label_events(event, data)
    m: dict[str, float] = {"n": float(len(events))}
    for k, name in enumerate(event.outcome_names):
        m[f"n_{name}"] = float(np.sum(events.outcome == k))
    if not len(events):
        return m | {"accuracy": float("nan"), "prior_accuracy": float("nan")}
    m["accuracy"] = float(np.mean(predict_outcomes(event, model, events) == events.outcome))
    m["prior_accuracy"] = float(np.mean(events.prior == events.outcome))
    decided = _training_set(event, events)
    if model is not None and len(decided):
        p = np.clip(model.probabilities(event.features(decided.pre)), 1e-12, 1.0)
        m["log_loss"] = float(log_loss(decided.outcome, p / p.sum(axis=1, keepdims=True),
                                       labels=list(range(len(event.outcomes)))))
    return m


def fit_events(task: Task | None, data: Any, min_events: int | None = None, seed: int = 0) -> dict[str, EventModel | None]:
    """{event name: its learned model or None} for every event the task declares."""
    if task is None:
        return {}
    return {e.name: fit_event_model(e, data, min_events, seed=seed) for e in task.events}


def event_metrics(task: Task | None, models: dict[str, EventModel | None], test: Any) -> dict[str, float]:
    """``events/<name>/...``: whether a model was learned, its training figures, and the
    predictor's scores on the held-out real events of ``test`` (``test_*``)."""
    m: dict[str, float] = {}
    for event in task.events if task is not None else ():
        model = models.get(event.name)
        key = f"events/{event.name}/"
        m[key + "learned"] = float(model is not None)
        if model is not None:
            m.update({key + k: v for k, v in model.metrics().items()})
        m.update({key + f"test_{k}": v for k, v in score_events(event, model, test).items()})
    return m
