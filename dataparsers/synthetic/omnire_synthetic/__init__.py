"""Synthetic driving scenes with ground truth, written in the processed-scene format."""
