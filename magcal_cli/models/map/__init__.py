"""Huang et al. 2025's joint MAP: one magnetometer's fit, its effects, start values and the joint fit of many."""
