"""Evaluation: metrics and benchmarks of retrieval and editing against published protocols."""
