"""Streaming outputs of ``splidar run`` on a Dask input, and the restart that skips strips.

The reconstruction's strips (``reconstruction/_tiled.py``) hand their core points to a
:class:`StripStore` as each finishes; it writes them at once and forgets them:

- ``points.parquet/tile=NNNN/part-0.parquet``: the strip's points (pyarrow; a Hive
  partition per strip, so ``pyarrow.parquet.read_table("points.parquet")`` or
  ``pandas.read_parquet`` read them all, with a ``tile`` column);
- ``maps.zarr``: ``depth_bin`` (rows, cols, K_s), ``intensity`` (rows, cols, K_s, L)
  and ``label`` (rows, cols, K_s), each strip writing its rows;
- ``labels/NNNN.npz``: the strip's labels pass (labels, marginals, neighbours' shading,
  the strip's own labels with its margins), ``labels/NNNN.resid.npz`` its residuals
  behind the std's smoothing-bias term (one term for the image: a restart needs every
  strip's);
- ``detection/``: the run's Detection (:func:`save_detection`: its saliency and mask
  in ``detection/maps.zarr`` when they are in memory, the rest pickled), so that a
  restart skips the detection too;
- ``surfaces.zarr``: the surfaces' data the strips' tasks read (rows sorted by image
  row), when the workers see the folder;
- ``manifest.json``: the run's key (input and options) and the strips finished, with
  what the assembled history needs. It is rewritten (atomically) after a strip's files.

The folder is the run's resume folder (``.OUT.resume`` beside the output): a run that is
killed leaves it; the next run with the same key skips the strips the manifest lists
(a different key starts afresh). Every file is written to a temporary name and renamed,
so a strip killed while writing is simply not listed and is computed again.
"""

from __future__ import annotations

import importlib
import io
import json
import os
import pickle
import shutil
from pathlib import Path
from types import MappingProxyType

import numpy as np

from ._files import atomic_path, savez
from ._validation import SplidarError

__all__ = ["StripStore", "load_detection", "read_points", "save_detection"]

_EXTRA = "pip install 'splidar[dask]' (or 'splidar[distributed]')"


def _pyarrow():
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise SplidarError(
            f"streaming the points of a Dask input to Parquet needs pyarrow: {_EXTRA}"
        ) from None
    return pa, pq


def _replace_json(path: Path, obj) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj))


class StripStore:
    """Where a streamed run keeps each finished strip (see the module docstring).

    Parameters
    ----------
    folder : path
        The resume folder (created; emptied when its manifest's key differs).
    key : str
        Identifies the run (input file and every option): a rerun with the same key
        resumes, any other starts afresh.
    image_shape : (rows, cols)
    n_slots, n_wavelengths : int
        ``K_s`` and ``L`` of the maps.
    bin_width_ps : float or None
        Adds a ``depth_m`` column when known.
    workers_see_folder : bool
        The workers can read files the calling process writes in ``folder`` (threads, a
        LocalCluster): the strips' surfaces are then written once to
        ``folder/surfaces.zarr`` (:attr:`surfaces_folder`) and each task reads its own,
        instead of travelling in the task graph.
    """

    def __init__(self, folder, key: str, image_shape, n_slots: int, n_wavelengths: int, *,
                 bin_width_ps=None, workers_see_folder: bool = True):  # fmt: skip
        _pyarrow()
        self.folder = Path(folder)
        self.surfaces_folder = self.folder if workers_see_folder else None
        self.key, self.image_shape = key, tuple(image_shape)
        self.n_slots, self.n_wavelengths = int(n_slots), int(n_wavelengths)
        self.bin_width_ps = bin_width_ps
        self.manifest, self.resumed = None, ()

    def begin(self, cores) -> None:
        """Open the folder for strips of these ``cores``: resume when the manifest has the
        same key and cores, else start afresh. The maps are chunked by strip (the first
        core's rows), so no two strips write one chunk."""
        import zarr

        cores = [list(map(int, c)) for c in cores]
        man = self.folder / "manifest.json"
        old = json.loads(man.read_text()) if man.is_file() else None
        if not all((self.folder / d).is_dir() for d in ("labels", "points.parquet", "maps.zarr")):
            old = None  # moved into an output that was not finished (interrupted at the end)
        if old is None or old.get("key") != self.key or old.get("cores") != cores:
            if self.folder.exists():  # afresh, but the detection (its own key) stays
                for p in self.folder.iterdir():
                    if p.name != "detection":
                        shutil.rmtree(p) if p.is_dir() else p.unlink()
            self.folder.mkdir(parents=True, exist_ok=True)
            (self.folder / "labels").mkdir()
            (self.folder / "points.parquet").mkdir()
            (R, C), K, L = self.image_shape, self.n_slots, self.n_wavelengths
            g = zarr.open_group(str(self.folder / "maps.zarr"), mode="w")
            ch = cores[0][1] - cores[0][0]
            for name, shape, dtype, fill in (
                ("depth_bin", (R, C, K), "f8", np.nan),
                ("intensity", (R, C, K, L), "f8", np.nan),
                ("label", (R, C, K), "i8", -1),
            ):
                g.create_array(name, shape=shape, chunks=(ch,) + shape[1:], dtype=dtype,
                               fill_value=fill)  # fmt: skip
            old = {"key": self.key, "cores": cores, "finished": {}}
            _replace_json(man, old)
        # a strip listed whose points file is gone is computed again
        old["finished"] = {n: m for n, m in old["finished"].items() if self._part(int(n)).is_file()}
        self.manifest = old
        self.resumed = tuple(sorted(int(n) for n in old["finished"]))

    # the labels pass -------------------------------------------------------------
    def labels(self, n: int):
        """``(labels, marginals, h_nb, own)`` of strip ``n``'s labels pass, or None."""
        p = self.folder / "labels" / f"{n:04d}.npz"
        if not p.is_file():
            return None
        with np.load(p) as z:
            if "own" not in z:
                return None
            h_nb = z["h_nb"] if "h_nb" in z else None
            return z["label"], z["marginals"], h_nb, z["own"]

    def put_labels(self, n: int, result) -> None:
        u, marg, h_nb, own = result
        arrays = dict(label=u, marginals=marg, own=own)
        if h_nb is not None:
            arrays["h_nb"] = h_nb
        savez(self.folder / "labels" / f"{n:04d}.npz", arrays, compress=False)

    def residuals(self, n: int):
        """Strip ``n``'s residuals behind the std's smoothing-bias term, or None."""
        p = self.folder / "labels" / f"{n:04d}.resid.npz"
        if not p.is_file():
            return None
        with np.load(p) as z:
            return z["e2"], z["knv"]

    def put_residuals(self, n: int, resid) -> None:
        e2, knv = resid
        savez(self.folder / "labels" / f"{n:04d}.resid.npz", dict(e2=e2, knv=knv), compress=False)

    # the intensities ---------------------------------------------------------------
    def _part(self, n: int) -> Path:
        return self.folder / "points.parquet" / f"tile={n:04d}" / "part-0.parquet"

    def fitted(self, n: int):
        """``(columns, meta)`` of a finished strip, or None."""
        meta = self.manifest["finished"].get(str(n))
        if meta is None:
            return None
        _, pq = _pyarrow()
        t = pq.read_table(self._part(n))
        L = sum(c.startswith("intensity_") and not c.startswith("intensity_std") for c in
                t.column_names)  # fmt: skip
        cols = {c: t.column(c).to_numpy() for c in ("surface", "label", "label_confidence")}
        for name in ("intensity", "intensity_std"):
            cols[name] = np.stack([t.column(f"{name}_{i}").to_numpy() for i in range(L)], axis=1)
        return cols, meta

    def put_fit(self, n: int, core, points: dict, meta: dict) -> None:
        """Write strip ``n``'s points (Parquet) and its rows of the maps (Zarr), then
        list it as finished."""
        import zarr

        pa, pq = _pyarrow()
        cols = {k: points[k] for k in ("surface", "row", "col", "depth_bin", "layer")}
        if self.bin_width_ps is not None:
            from .cube import SPEED_OF_LIGHT

            cols["depth_m"] = points["depth_bin"] * self.bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2
        for name in ("intensity", "intensity_std"):
            for i in range(points[name].shape[1]):
                cols[f"{name}_{i}"] = points[name][:, i]
        cols["label"] = points["label"]
        cols["label_confidence"] = points["label_confidence"]
        part = self._part(n)
        part.parent.mkdir(exist_ok=True)
        with atomic_path(part) as tmp:  # a hidden name: Parquet readers skip it
            pq.write_table(pa.table({k: np.asarray(v) for k, v in cols.items()}), tmp)
        r0, r1 = core
        g = zarr.open_group(str(self.folder / "maps.zarr"), mode="r+")
        rr, cc, ll = points["row"] - r0, points["col"], points["layer"]
        depth = np.full((r1 - r0,) + g["depth_bin"].shape[1:], np.nan)
        inten = np.full((r1 - r0,) + g["intensity"].shape[1:], np.nan)
        label = np.full((r1 - r0,) + g["label"].shape[1:], -1, np.int64)
        depth[rr, cc, ll] = points["depth_bin"]
        inten[rr, cc, ll] = points["intensity"]
        label[rr, cc, ll] = points["label"]
        g["depth_bin"][r0:r1] = depth
        g["intensity"][r0:r1] = inten
        g["label"][r0:r1] = label
        self.manifest["finished"][str(n)] = meta
        _replace_json(self.folder / "manifest.json", self.manifest)


def _proxy(d: dict) -> MappingProxyType:
    return MappingProxyType(d)


def save_detection(folder, key: str, detection) -> None:
    """Keep ``detection`` in ``folder/detection`` for a restart of the run ``key``: the
    saliency and mask in Zarr (chunked by 64 rows) when they are NumPy arrays (a
    detection with ``store=`` already has them on disk, the pickle refers to them),
    the rest (surface table, background, null model, options) pickled. Written under a
    temporary name and renamed: a run killed meanwhile leaves no detection."""
    import dataclasses

    import zarr

    final = Path(folder) / "detection"
    tmp = Path(folder) / "detection.tmp"
    for p in (tmp, final):
        if p.exists():
            shutil.rmtree(p)
    tmp.mkdir(parents=True)
    swap = {}
    for name in ("saliency", "mask"):
        a = getattr(detection, name)
        if isinstance(a, np.ndarray):
            z = zarr.create_array(str(tmp / f"{name}.zarr"), shape=a.shape, dtype=a.dtype,
                                  chunks=(min(64, a.shape[0]),) + a.shape[1:])  # fmt: skip
            z[...] = a
            swap[name] = None
    det = dataclasses.replace(detection, **swap)
    with open(tmp / "detection.pkl", "wb") as f:
        pickler = pickle.Pickler(f, protocol=pickle.HIGHEST_PROTOCOL)
        pickler.dispatch_table = {MappingProxyType: lambda m: (_proxy, (dict(m),))}
        pickler.dump((key, sorted(swap), det))
    os.replace(tmp, final)


# What a kept detection's pickle may name: splidar's own result classes, NumPy's array
# reconstruction, and (for a detection with ``store=``) the Zarr array handles and their
# codecs. Anything else (``os.system``, ``builtins.eval``, ...) is refused before it is
# called: a resume folder is read back like any other file, and splidar never runs code
# from a file (docs/reliability.md).
_ALLOWED = {
    ("splidar._stream", "_proxy"),
    ("splidar.library", "SpectralLibrary"),
    ("numpy", "dtype"),
    ("numpy._core.numeric", "_frombuffer"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("pathlib", "PosixPath"),
    ("pathlib", "WindowsPath"),
    ("pathlib", "Path"),
}
_ALLOWED_MODULES = ("splidar.detection._result", "splidar.detection._threshold")
_ALLOWED_PREFIXES = ("zarr.", "numcodecs.")


class _RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the names a kept Detection needs."""

    def find_class(self, module: str, name: str):
        ok = (module, name) in _ALLOWED or module in _ALLOWED_MODULES
        if not ok and module.startswith(_ALLOWED_PREFIXES):
            ok = isinstance(getattr(importlib.import_module(module), name, None), type)
        if not ok:
            raise SplidarError(
                f"the kept detection in the resume folder names {module}.{name}, which a "
                "splidar detection never holds; delete the folder .OUT.resume beside the "
                "output (the run then starts afresh)"
            )
        return super().find_class(module, name)


def load_detection(folder, key: str):
    """The Detection :func:`save_detection` kept for the run ``key``, or None (none kept,
    or another run's). Its saliency and mask are read back into memory."""
    import dataclasses

    import zarr

    d = Path(folder) / "detection"
    if not (d / "detection.pkl").is_file():
        return None
    data = (d / "detection.pkl").read_bytes()
    old_key, swapped, det = _RestrictedUnpickler(io.BytesIO(data)).load()
    if old_key != key:
        return None
    arrays = {n: zarr.open_array(str(d / f"{n}.zarr"), mode="r")[...] for n in swapped}
    return dataclasses.replace(det, **arrays)


def read_points(path) -> dict:
    """The points of a ``points.parquet`` folder as columns, sorted by ``surface``."""
    _, pq = _pyarrow()
    t = pq.read_table(Path(path))
    order = np.argsort(t.column("surface").to_numpy(), kind="stable")
    return {c: np.asarray(t.column(c).to_numpy())[order] for c in t.column_names if c != "tile"}
