"""Fourier pseudo-spectral building blocks: real FFTs usable inside numba kernels with their
adjoints (:mod:`.fft1d`) and exponential time-differencing coefficients (:mod:`.etdrk`)."""
