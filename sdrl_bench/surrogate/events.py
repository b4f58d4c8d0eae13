"""The learned event model of a Dyna surrogate: which of the surrogate's events end in a crash.

A dynamics model fitted on flight rows says nothing about what happens at touchdown; the
surrogate's rules (``envs.lunar_lander.task``) decide crash or survive from the pre-impact
speed and tilt alone, in a flat world. The real env's ground is random off the pad, and an
agent trained in the flat world lands there and crashes (``benchmarks/lunar_lander_terrain.py``).
A Dyna loop brings back the agent's own touchdowns; this module fits, on those the rules let
survive, the probability that the real env ended them in a crash, as a function of the
pre-impact state (the spec says which features: ``EnvSpec.event_features``). The surrogate
then ends such an event in a crash with that probability (``surrogate.vec.SurrogateVecEnv``).

The classifier is scikit-learn's ``LogisticRegression`` on standardized features (L2, C=1):
a few dozen events, two classes, a smooth probability; nothing here is hand-written but the
bookkeeping.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sdrl_bench.envs.base import EnvSpec


@dataclass
class EventModel:
    """P(crash | pre-event features), fitted on real events."""

    classifier: Any
    """A fitted scikit-learn pipeline (scaler + logistic regression)."""
    feature_names: tuple[str, ...]
    n_events: int
    n_crashes: int
    train_accuracy: float
    train_log_loss: float

    def probability(self, features: np.ndarray) -> np.ndarray:
        x = np.asarray(features, dtype=float)
        classes = list(self.classifier.classes_)
        return self.classifier.predict_proba(x)[:, classes.index(True)] if True in classes else np.zeros(len(x))

    def metrics(self) -> dict[str, float]:
        return {"n_events": float(self.n_events), "n_crashes": float(self.n_crashes),
                "train_accuracy": self.train_accuracy, "train_log_loss": self.train_log_loss}

    def to_dict(self) -> dict[str, Any]:
        """The fitted model as plain numbers (logged beside each round's fit)."""
        scaler, logit = self.classifier[0], self.classifier[-1]
        return {"kind": "logistic", "features": list(self.feature_names), "mean": scaler.mean_.tolist(),
                "scale": scaler.scale_.tolist(), "coef": logit.coef_[0].tolist(), "intercept": float(logit.intercept_[0]),
                **self.metrics()}


def fit_event_model(spec: EnvSpec, data: Any, min_events: int = 8, c: float = 1.0) -> EventModel | None:
    """The event model fitted on the events of ``data`` (a ``data.Transitions``), or None when
    the env has no learned events, or the data hold fewer than ``min_events`` of them or only
    one outcome (the surrogate's rules alone decide then)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.metrics import log_loss
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    got = spec.event_data(data)
    if got is None:
        return None
    features, crashed = np.asarray(got[0], dtype=float), np.asarray(got[1], dtype=bool)
    if len(crashed) < min_events or crashed.all() or not crashed.any():
        return None
    clf = make_pipeline(StandardScaler(), LogisticRegression(C=c, max_iter=1000)).fit(features, crashed)
    p = clf.predict_proba(features)[:, 1]
    return EventModel(clf, tuple(spec.event_feature_names), len(crashed), int(crashed.sum()),
                      float(np.mean((p >= 0.5) == crashed)), float(log_loss(crashed, p, labels=[False, True])))
