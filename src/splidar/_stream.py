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
- ``manifest.json``: the run's key (input and options) and the strips finished, with
  what the assembled history needs. It is rewritten (atomically) after a strip's files.

The folder is the run's resume folder (``.OUT.resume`` beside the output): a run that is
killed leaves it; the next run with the same key skips the strips the manifest lists
(a different key starts afresh). Every file is written to a temporary name and renamed,
so a strip killed while writing is simply not listed and is computed again.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from ._validation import SplidarError

__all__ = ["StripStore", "read_points"]

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
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj))
    os.replace(tmp, path)


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
    """

    def __init__(self, folder, key: str, image_shape, n_slots: int, n_wavelengths: int, *,
                 bin_width_ps=None):  # fmt: skip
        _pyarrow()
        self.folder = Path(folder)
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
            if self.folder.exists():
                shutil.rmtree(self.folder)
            self.folder.mkdir(parents=True)
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
        self._save(self.folder / "labels" / f"{n:04d}.npz", arrays)

    def residuals(self, n: int):
        """Strip ``n``'s residuals behind the std's smoothing-bias term, or None."""
        p = self.folder / "labels" / f"{n:04d}.resid.npz"
        if not p.is_file():
            return None
        with np.load(p) as z:
            return z["e2"], z["knv"]

    def put_residuals(self, n: int, resid) -> None:
        e2, knv = resid
        self._save(self.folder / "labels" / f"{n:04d}.resid.npz", dict(e2=e2, knv=knv))

    @staticmethod
    def _save(path: Path, arrays: dict) -> None:
        tmp = path.with_name(path.name[: -len(".npz")] + ".tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)

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
        tmp = part.with_name("part-0.parquet.tmp")
        pq.write_table(pa.table({k: np.asarray(v) for k, v in cols.items()}), tmp)
        os.replace(tmp, part)
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


def read_points(path) -> dict:
    """The points of a ``points.parquet`` folder as columns, sorted by ``surface``."""
    _, pq = _pyarrow()
    t = pq.read_table(Path(path))
    order = np.argsort(t.column("surface").to_numpy(), kind="stable")
    return {c: np.asarray(t.column(c).to_numpy())[order] for c in t.column_names if c != "tile"}
