"""Tests run in float64 (diffrax-style): enabled before any array is made."""
import jax

jax.config.update("jax_enable_x64", True)
