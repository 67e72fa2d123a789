"""Evaluation: the baseline denoisers, metrics, Table 1 and the HTML report."""
