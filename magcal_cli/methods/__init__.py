"""The calibration methods: the one METHODS table, the automatic choice, and the runs that fit a whole log."""
