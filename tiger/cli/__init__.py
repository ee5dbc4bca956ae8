"""The ``tiger`` command line."""

#: Nothing is re-exported here: import the modules (e.g. ``tiger.cli.<module>``) directly.
__all__: list[str] = []
