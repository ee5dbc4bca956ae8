"""Small shared helpers (atomic file writes, lazy imports)."""

#: Nothing is re-exported here: import the modules (e.g. ``tiger.utils.<module>``) directly.
__all__: list[str] = []
