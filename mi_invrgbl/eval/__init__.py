"""Evaluation library: metrics, baselines and scoring of fitted scenes."""
