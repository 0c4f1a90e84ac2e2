"""Fault injectors: named crash points and the power-loss simulator (used by the tests)."""

__all__: list[str] = []
