"""The ``dran-edge`` command line (``app``) and its sub-commands (``commands``)."""
