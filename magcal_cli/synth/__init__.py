"""The simulator: recordings with known truth, their scenarios and effects, and the log writers."""
