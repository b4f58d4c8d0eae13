"""Hydra configs shipped with the package (``pkg://sdrl_bench.conf``)."""
