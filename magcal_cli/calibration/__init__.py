"""The calibration document: its types, its effect and diagnosis blocks, the run result, assembly and apply."""
