"""Foundations every layer shares: the numbers and names (``constants``, JAX-free), array types and
the frame/symbol legend (``types``), gradient-safe helpers (``math``), results on disk (``io``), the
MJX import (``mjx``) and what a result file records of its origin (``provenance``)."""
