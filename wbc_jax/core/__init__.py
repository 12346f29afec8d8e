"""Foundations every layer shares: the numbers and names (``constants``, JAX-free), array types and
the frame/symbol legend (``types``), gradient-safe helpers (``math``), results on disk (``io``), the
MJX import (``mjx``), what a result file records of its origin (``provenance``) and what a check
script does with its verdict (``checks``)."""
