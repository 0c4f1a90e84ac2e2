"""Evaluation of place recognition on data sets: k-NN baselines versus SPRINT."""
