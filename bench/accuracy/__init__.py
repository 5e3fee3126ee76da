"""Accuracy: scores against named baselines and targets, on renders and real photos."""
