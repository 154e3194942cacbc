"""Plastic springs: moved to :mod:`diffpen.terms.plastic` (this module re-exports it)."""
from .terms.plastic import AUX_KEY, TERMS, rest_update  # noqa: F401

__all__ = ["rest_update", "AUX_KEY", "TERMS"]
