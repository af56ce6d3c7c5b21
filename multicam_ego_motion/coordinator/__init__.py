"""The coordinator: places the graph's nodes on M worker processes (paper section 3) and keeps them running."""
