"""Measuring the product: `ego-motion bench` (timing.py: sequential vs the graph, rate mode,
camera rate, live vs offline, the targets; transport_floor.py: the same graph with quarters
that do no work), `ego-motion profile` (profile_table.py: where
the CPU goes) and `ego-motion matrix` (accuracy_matrix.py: the accuracy a change is judged by)."""
