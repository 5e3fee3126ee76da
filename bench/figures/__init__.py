"""Figures: the docs/img pictures that are drawn by code."""
