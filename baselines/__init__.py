"""The shipped baseline plugins, one file per method (installed as the package `kgnavbench_baselines`).

Files starting with `_` are not plugins. To add a method, copy `random_walk.py` into a `baselines/`
folder of your working directory (or here) and change it; `kgnavbench methods` lists it.
"""
