"""The ``shgm-slam`` command's entry point (also ``python -m shgm_slam``).

The command line loads numpy, gtsam and pydantic (about a second) inside the interrupt guard: a Ctrl-C that
lands while it loads ends the command with "interrupted" and exit code 130, as one during a command does,
not with a traceback.
"""

from __future__ import annotations

import sys

from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE


def main() -> None:
    """Load the command line and run it (``shgm_slam.cli.main``)."""
    try:
        from shgm_slam.cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        raise SystemExit(INTERRUPTED_EXIT_CODE) from None
    cli_main()


if __name__ == "__main__":
    main()
