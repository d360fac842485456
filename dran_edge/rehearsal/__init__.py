"""A fleet of real robot daemons through a recorded mission, with faults (docs/rehearsal.md)."""
