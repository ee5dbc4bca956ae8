"""The ``tiger`` command line."""
