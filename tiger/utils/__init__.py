"""Small shared helpers (atomic file writes, lazy imports)."""
