"""``python -m cifilter``: see :mod:`cifilter.cli.main`."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
