"""Placeholder: overwritten by benchmarks/fit_labeler.py --write."""

PAPER_PRESET: dict = {}
