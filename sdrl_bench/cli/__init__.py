"""The edge: the only code that reads a DictConfig, composes configs or calls ``instantiate``.

``build`` turns a composed config into typed jobs; the entry modules (``main``, ``search``,
``report``) parse, build, call the library and print.
"""

CONFIG_MODULE = "sdrl_bench.conf"
CONFIG_PATH = "pkg://" + CONFIG_MODULE
