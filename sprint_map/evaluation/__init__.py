"""Evaluation of place recognition on data sets: k-NN baselines versus SPRINT."""

__all__: list[str] = []
