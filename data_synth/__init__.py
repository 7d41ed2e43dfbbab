"""Synthetic scans with known ground truth (objects, rigs, observations) for testing jaxrefl."""
