"""Kept only for `_variational.py`, which imports `describe` from here: every check now
lives in `_checks.py`. Remove once `_variational.py` imports from `_checks`."""

from ._checks import describe as describe
