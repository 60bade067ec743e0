"""Estimation maths shared by the selection stages: information model, covariances, selection.

Pure numpy/scipy/gtsam; no I/O.
"""
