"""The edge: the only code that reads a DictConfig, composes configs or calls ``instantiate``.

``build`` turns a composed config into typed jobs; the entry modules (``main``, ``search``,
``report``) parse, build, call the library and print.
"""

CONFIG_MODULE = "sdrl_bench.conf"
CONFIG_PATH = "pkg://" + CONFIG_MODULE

NOT_OF_THE_RESULT = ("resume", "progress_bar")
"""Config keys that change no job's result: a job's config key (``build.config_key``) and a
sweep's (``callbacks.sweep_key``) leave them out, so adding ``resume=true`` or
``progress_bar=false`` to a rerun keeps it the same job and the same sweep."""
