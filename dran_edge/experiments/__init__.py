"""Experiment drivers: fleets of agents, baselines and benchmark suites (shells around the core)."""
