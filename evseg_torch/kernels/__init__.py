"""Compiled kernels (Numba, the optional ``fast`` extra) of steps that also exist as tensor or NumPy code.

Each module here is the compiled form of one step, imported only when :func:`evseg_torch.backend.kernel`
chooses it (so importing evseg_torch never loads Numba); :mod:`~evseg_torch.kernels.common` holds the
helpers they share. The tensor or NumPy code beside each step is its reference, and the tests hold each
kernel to it.
"""
