"""Private file writing: reproducible ``.npz`` bytes and atomic replacement.

``numpy.savez_compressed`` stamps each zip member with the current time, so the same
arrays written a second later differ byte for byte. :func:`savez` writes the same
format with a fixed timestamp (1980-01-01), so the same result gives the same bytes.
Every writer here writes beside the destination and renames at the end
(:func:`atomic_path`): an interrupted write leaves the previous file or none, never
half a file.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_path", "savez"]

_EPOCH = (1980, 1, 1, 0, 0, 0)  # the earliest date a zip file can hold


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def savez(path: str | os.PathLike, arrays: Mapping[str, Any], *, compress: bool = True) -> Path:
    """Write ``arrays`` as a ``.npz`` readable by :func:`numpy.load`, reproducibly and atomically.

    Members are written in the order given, each with a fixed timestamp and without
    pickle (object arrays raise ``ValueError``).
    """
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=method, allowZip64=True) as zf:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
                info.compress_type = method
                info.external_attr = 0o644 << 16
                with zf.open(info, "w", force_zip64=True) as fh:
                    np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)
    return Path(path)
