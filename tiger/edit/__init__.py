"""Editing and deletion of retrieved objects (paper §3.2 and appendix; SPEC §6)."""
