"""Scoring estimates against ground truth: metrics, alignment, reports."""
