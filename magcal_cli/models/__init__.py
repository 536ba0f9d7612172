"""Estimators: sensor residual models, the one least-squares solver and the calibration methods."""
