"""``python -m splidar``: the same as the ``splidar`` command."""

from .cli import entry

if __name__ == "__main__":
    entry()
