"""Benchmarks shipped with the package, behind ``adjointsim bench``.

``work-precision`` (:mod:`.work_precision`): error against run time of the spectral ETDRK
solvers, their NumPy ETDRK4 baseline and (when installed) exponax. Nothing here imports torch
or jax at module level; the peer libraries load inside the functions that use them.
"""
