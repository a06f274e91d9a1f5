"""Proprioceptive state estimator (node state_estimator) and Terrain Compliance Estimator (node tce)."""
