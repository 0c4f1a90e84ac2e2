"""Foundations every layer may use: array types, atomic files, config dicts, input rules, FAISS."""

__all__: list[str] = []
