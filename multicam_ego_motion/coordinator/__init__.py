"""The coordinator: places the graph's nodes on worker processes and keeps them running."""
