"""``python -m splidar``: the same as the ``splidar`` command."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
