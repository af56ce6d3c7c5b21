"""Tooling around the estimation graph: bags, scenarios, evaluation, coordinator, CLI."""
