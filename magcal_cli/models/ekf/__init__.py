"""The EKF baselines: Kok & Schoen 2016 (likelihood) and Wu et al. 2018 (augmented state), and their effects."""
