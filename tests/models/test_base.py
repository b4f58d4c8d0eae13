"""Loading a saved model by its kind: the loader registry."""

from __future__ import annotations

import json

import pytest

from sdrl_bench import ConfigError
from sdrl_bench.models import base


def test_unknown_kind_names_the_file_and_the_known_kinds(tmp_path):
    path = tmp_path / "model.json"
    path.write_text(json.dumps({"kind": "gp"}))
    with pytest.raises(ConfigError, match=r"model\.json: model kind 'gp' is not supported \(sindy, nn"):
        base.load_model(path)


def test_a_registered_kind_is_loaded_by_its_class(tmp_path, monkeypatch):
    class Constant:
        @classmethod
        def from_saved(cls, data, path):
            obj = cls()
            obj.value, obj.path = data["value"], path
            return obj

    monkeypatch.setattr(base, "_LOADERS", dict(base._LOADERS))
    base.register_loader("constant", Constant)
    path = tmp_path / "model.json"
    path.write_text(json.dumps({"kind": "constant", "value": 3}))
    model = base.load_model(str(path))
    assert isinstance(model, Constant) and model.value == 3 and model.path == path
