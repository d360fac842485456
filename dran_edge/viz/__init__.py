"""What the fleet estimates, for Foxglove: live from a daemon, or as an MCAP file of a run (docs/viz.md)."""
