"""GTSAM factors and noise models: scan-match between-factors, rendezvous factors, kernels."""
