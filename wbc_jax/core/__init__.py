"""Foundations every layer shares: the numbers and names (``constants``, JAX-free), array types and
the frame/symbol legend (``types``), gradient-safe helpers (``math``), results on disk (``io``), the
one loader of input files (``loader``), config fields declared once with their valid values
(``options``), the package data (``assets``), the MJX import (``mjx``), several processes joined by
jax.distributed (``processes``), what a result file records of its origin (``provenance``), what
a check script does with its verdict (``checks``) and C++ sources built into XLA FFI libraries (``native_build``)."""
