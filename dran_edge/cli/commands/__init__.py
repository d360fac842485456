"""Sub-commands of the ``dran-edge`` CLI, one module each.

Each module defines ``HELP`` (one line), ``build_parser(prog) -> argparse.ArgumentParser``
and ``run(args) -> int``. They are imported only when their sub-command runs.
"""
