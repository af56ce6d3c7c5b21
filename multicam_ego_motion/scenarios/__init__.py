"""Synthetic scenarios: trajectories, an indoor world, a ray-casting renderer and the bag writer."""
