"""``tracking.check_store``'s look at a tracking server before a job's libraries load, against a
real HTTP server on 127.0.0.1: any answer counts as reached, credentials in the URI go as Basic
auth (as MLflow sends them), and a server that does not answer is one line with the password
hidden."""

from __future__ import annotations

import http.server
import socket
import threading

import pytest

from sdrl_bench import ConfigError, tracking


class _Health(http.server.BaseHTTPRequestHandler):
    seen: list = []
    status = 200

    def do_GET(self):  # noqa: N802 (http.server's name)
        _Health.seen.append((self.path, self.headers.get("Authorization")))
        self.send_response(_Health.status)
        self.end_headers()

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    srv = http.server.HTTPServer(("127.0.0.1", 0), _Health)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    _Health.seen, _Health.status = [], 200
    yield srv.server_address[1]
    srv.shutdown()
    srv.server_close()


@pytest.mark.parametrize("status", [200, 401, 404])
def test_a_server_that_answers_is_reached_whatever_its_status(server, status):
    _Health.status = status
    tracking.check_store(f"http://127.0.0.1:{server}", reach=True)
    assert _Health.seen == [("/health", None)]


def test_credentials_in_the_uri_are_sent_as_basic_auth(server):
    tracking.check_store(f"http://u:pw@127.0.0.1:{server}/", reach=True)
    assert _Health.seen == [("/health", "Basic dTpwdw==")]  # base64 of u:pw


def test_a_server_that_does_not_answer_is_one_line_without_its_password():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    with pytest.raises(ConfigError) as err:
        tracking.check_store(f"http://u:secret@127.0.0.1:{port}", "MLFLOW_TRACKING_URI", reach=True)
    assert str(err.value) == (f"MLFLOW_TRACKING_URI: the tracking server at http://u:***@127.0.0.1:{port} does not "
                              "answer ([Errno 111] Connection refused); start it, or fix the URI")


def test_a_stop_caps_mlflows_waits_on_a_server_and_keeps_a_users_lower_setting(monkeypatch):
    """What a stop signal's hooks do to MLflow's HTTP settings (``tracking.client.STOP_SERVER_WAITS``,
    read by MLflow on every request): the defaults capped, a user's lower value kept, a value
    MLflow could not read replaced; as MLflow itself reads them afterwards."""
    from mlflow.environment_variables import (MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR, MLFLOW_HTTP_REQUEST_MAX_RETRIES,
                                              MLFLOW_HTTP_REQUEST_TIMEOUT)

    import sdrl_bench

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")  # the user's, lower than the cap
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "600")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR", "x")
    assert MLFLOW_HTTP_REQUEST_TIMEOUT.get() == 600
    sdrl_bench.run_stop_hooks()  # what the stop signal's handler runs first
    assert MLFLOW_HTTP_REQUEST_MAX_RETRIES.get() == 0
    assert MLFLOW_HTTP_REQUEST_TIMEOUT.get() == 5
    assert MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR.get() == 1
    monkeypatch.delenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES")  # MLflow's default (7) is capped too
    sdrl_bench.run_stop_hooks()
    assert MLFLOW_HTTP_REQUEST_MAX_RETRIES.get() == 1


@pytest.mark.parametrize("given, hidden, bare", [
    ("http://alice:s3cr:et@127.0.0.1:5000/x?y=1", "http://alice:***@127.0.0.1:5000/x?y=1", "http://127.0.0.1:5000/x?y=1"),
    ("postgresql+psycopg2://u:p%40ss@db:5432/optuna", "postgresql+psycopg2://u:***@db:5432/optuna", None),
    ("mysql://root:pw@[::1]:3306/o", "mysql://root:***@[::1]:3306/o", None),
    ("http://bob@h:1", "http://bob@h:1", "http://h:1"),  # a user and no password: nothing to hide
    ("sqlite:////tmp/a:b@c.db", "sqlite:////tmp/a:b@c.db", None),  # a path, not a login
    ("journal:/tmp/j.log", "journal:/tmp/j.log", None),
    ("http://[::1", "http://[::1", "http://[::1"),  # not a URL: as it is
    # a database password with "/" in it, unescaped: SQLAlchemy (and so Optuna) reads it so
    ("postgresql://u:p/w@h/db?b=2&a=1", "postgresql://u:***@h/db?a=1&b=2", None),
])
def test_a_password_in_a_url_is_hidden_and_links_carry_no_login(given, hidden, bare):
    from sdrl_bench import redact, redact_arg
    from sdrl_bench.tracking import display_uri, without_credentials

    assert redact(given) == hidden
    if given.startswith("http"):  # the links: a UI's address, never a database's
        assert without_credentials(given) == bare
    assert redact_arg(f"tracking.uri={given}") == f"tracking.uri={hidden}" and redact_arg(given) == hidden
    assert redact_arg(f"--uri={given}") == f"--uri={hidden}"
    assert redact_arg(f"tracking.uri='{given}'") == f"tracking.uri='{hidden}'"  # quoted, as Hydra wants a comma
    if not given.startswith("sqlite"):
        assert display_uri(given) == hidden


def test_a_password_quoted_in_mlflows_error_message_is_hidden():
    from sdrl_bench.tracking.client import hide_password

    said = "MlflowException: API request to http://alice:p%40ss@h:5000/api/2.0/mlflow/runs/get failed (p@ss)"
    assert hide_password(said, "http://alice:p%40ss@h:5000") == (
        "MlflowException: API request to http://alice:***@h:5000/api/2.0/mlflow/runs/get failed (***)")
    assert hide_password(said, "sqlite:////tmp/s.db") == said
