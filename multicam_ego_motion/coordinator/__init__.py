"""Coordinator: places the quarter and arbiter nodes on M worker processes (paper section 3)."""
