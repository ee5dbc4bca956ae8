"""Evaluation: metrics and benchmarks of retrieval and editing against published protocols."""

#: Nothing is re-exported here: import the modules (e.g. ``tiger.eval.<module>``) directly.
__all__: list[str] = []
