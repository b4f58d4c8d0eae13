"""The one door to MLflow: the only package that imports mlflow.

``from sdrl_bench import tracking`` and call ``tracking.<function>``; the submodules hold the
client wrapper and store handling, fit logging, transfer logging, the SB3 writer and the
report's read side.
"""

from sdrl_bench.tracking.client import *  # noqa: F401,F403
