"""Where a study's Optuna storage is, from its URL alone: no optuna import, so that the
command line's check (``cli.precheck``) can find a local SQLite file and check it before the
search's libraries load."""

from __future__ import annotations

from pathlib import Path

DEFAULT_STORAGE = Path("mlruns") / "optuna.db"


def resolve_storage(url: str | None) -> str:
    """``None`` -> the project's SQLite file; relative SQLite and journal paths made absolute."""
    if not url:
        return f"sqlite:///{(Path.cwd() / DEFAULT_STORAGE).resolve()}"
    if url.startswith("sqlite:///") and not url.startswith("sqlite:////"):
        return f"sqlite:///{Path(url[len('sqlite:///'):]).resolve()}"
    if url.startswith("journal:"):
        return f"journal:{Path(url[len('journal:'):]).resolve()}"
    return url
