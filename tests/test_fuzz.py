"""Property-based tests (hypothesis) of the public API: random inputs never crash.

Valid random inputs give outputs that keep their invariants; random damage to a valid
file gives either the data or a :class:`SplidarError`, nothing else.

Profiles: ``ci`` (default; bounded so that the module takes well under a minute) and
``release`` (hundreds of examples per property; run before a release)::

    SPLIDAR_FUZZ=release python -m pytest tests/test_fuzz.py -p no:randomly
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

import splidar  # noqa: E402
from splidar import Cube, PointSet, SpectralLibrary, SplidarError  # noqa: E402
from splidar.cli import read_points  # noqa: E402
from splidar.export import write_csv, write_npz  # noqa: E402
from splidar.io import load, save  # noqa: E402
from splidar.simulate import simulate  # noqa: E402  (splidar.simulate can be the module)

_COMMON = {
    "deadline": None,
    "suppress_health_check": [HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    "derandomize": True,  # the same examples on every run: a CI failure reproduces
}
settings.register_profile("ci", max_examples=12, **_COMMON)
settings.register_profile("release", max_examples=2000, **{**_COMMON, "derandomize": False})
PROFILE = os.environ.get("SPLIDAR_FUZZ", "ci")
FAST = settings.get_profile(PROFILE)
# the pipeline properties run detection and reconstruction: fewer examples in CI
SLOW = settings(FAST, max_examples=max(FAST.max_examples // 3, 4))


# ---------------------------------------------------------------------------------------
# strategies
# ---------------------------------------------------------------------------------------
@st.composite
def cubes(draw, max_side: int = 6, max_bins: int = 40) -> Cube:
    rows = draw(st.integers(1, max_side))
    cols = draw(st.integers(1, max_side))
    n_l = draw(st.integers(1, 3))
    n_bins = draw(st.integers(4, max_bins))
    dtype = draw(st.sampled_from([np.uint8, np.uint16, np.uint32, np.int32, np.int64]))
    counts = draw(hnp.arrays(dtype, (rows, cols, n_l, n_bins), elements=st.integers(0, 50)))
    n_irf = draw(st.integers(1, min(n_bins, 9)))
    irf = draw(
        hnp.arrays(np.float64, (n_l, n_irf), elements=st.floats(0, 10, allow_subnormal=False))
    )
    irf[:, draw(st.integers(0, n_irf - 1))] += 1.0  # at least one positive sample per row
    kw = {}
    if draw(st.booleans()):
        kw["bin_width_ps"] = draw(st.floats(0.5, 1000))
    if draw(st.booleans()):
        kw["library"] = draw(
            hnp.arrays(np.float64, (draw(st.integers(1, 3)), n_l), elements=st.floats(0.1, 5))
        )
    return Cube(counts, irf=irf, **kw)


def scenes(max_side: int = 8):
    """Simulated scenes: random size, depths, PPP, SBR, wavelengths and seed."""

    @st.composite
    def build(draw):
        rows = draw(st.integers(2, max_side))
        cols = draw(st.integers(2, max_side))
        n_bins = draw(st.integers(30, 60))
        n_l = draw(st.integers(1, 3))
        seed = draw(st.integers(0, 2**16))
        rng = np.random.default_rng(seed)
        rr, cc = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        depth = rng.uniform(5, n_bins - 6, size=rr.size)
        truth = PointSet(
            row=rr.ravel(),
            col=cc.ravel(),
            depth_bin=depth,
            image_shape=(rows, cols),
            intensity=rng.uniform(0.5, 2.0, (rr.size, n_l)),
        )
        return simulate(
            truth,
            n_bins=n_bins,
            irf=splidar.gaussian_irf(draw(st.floats(1.0, 4.0))),
            ppp=draw(st.floats(0.5, 30)),
            sbr=draw(st.floats(0.1, 10)),
            rng=seed,
        )

    return build()


# ---------------------------------------------------------------------------------------
# Cube, simulate
# ---------------------------------------------------------------------------------------
@FAST
@given(cubes())
def test_cube_random_valid_input_keeps_counts_and_normalises_irf(cube):
    assert cube.counts.ndim == 4 and cube.counts.dtype.kind in "ui"
    assert cube.irf.shape[0] == cube.n_wavelengths
    assert cube.irf.shape[1] <= cube.n_bins
    np.testing.assert_allclose(cube.irf.sum(axis=1), 1.0, rtol=1e-12)
    assert np.all(cube.irf >= 0)


@FAST
@given(
    hnp.arrays(
        st.sampled_from([np.float64, np.float32]),
        hnp.array_shapes(min_dims=1, max_dims=5, min_side=0, max_side=4),
        elements=st.one_of(st.integers(-3, 300), st.floats(allow_nan=True, width=32)),
    ),
    hnp.arrays(np.float64, st.integers(0, 6), elements=st.floats(-1, 5, width=32)),
)
def test_cube_random_array_valid_or_splidar_error(counts, irf):
    """Any array as counts and IRF: a valid Cube or a SplidarError, nothing else."""
    try:
        cube = Cube(counts, irf=irf)
    except SplidarError:
        return
    assert np.all(np.asarray(cube.counts) >= 0)


@SLOW
@given(scenes())
def test_simulate_random_scene_counts_nonnegative_integers(sim):
    c = sim.cube.counts
    assert c.dtype.kind in "ui" and c.min() >= 0
    assert sim.cube.n_bins == c.shape[-1]
    assert np.all((sim.truth.depth_bin >= 0) & (sim.truth.depth_bin < sim.cube.n_bins))


# ---------------------------------------------------------------------------------------
# load / save
# ---------------------------------------------------------------------------------------
@FAST
@given(cube=cubes())
def test_save_load_random_cube_round_trip(cube, tmp_path_factory):
    p = tmp_path_factory.mktemp("rt") / "c.npz"
    save(cube, p)
    back = load(p)
    np.testing.assert_array_equal(back.counts, cube.counts)
    np.testing.assert_allclose(back.irf, cube.irf, rtol=1e-12)
    assert back.bin_width_ps == cube.bin_width_ps


def _valid_npz() -> bytes:
    bio = io.BytesIO()
    rng = np.random.default_rng(0)
    np.savez(bio, counts=rng.poisson(1, (3, 4, 16)).astype(np.uint16), irf=[0.2, 1.0, 0.2])
    return bio.getvalue()


def _valid_mat_h5() -> dict[str, bytes]:
    import tempfile

    import h5py
    import scipy.io

    rng = np.random.default_rng(0)
    counts = rng.poisson(1, (3, 4, 16)).astype(np.uint16)
    cells = np.empty((2, 3), dtype=object)
    for i in range(2):
        for j in range(3):
            cells[i, j] = rng.integers(0, 30, (i + j, 1)).astype(np.uint16)
    out = {}
    with tempfile.TemporaryDirectory() as t:
        scipy.io.savemat(f"{t}/a.mat", {"counts": counts, "irf": [0.2, 1.0, 0.2]})
        scipy.io.savemat(f"{t}/b.mat", {"Ts": cells}, do_compression=True)
        with h5py.File(f"{t}/c.h5", "w") as f:
            f["counts"] = counts
            f["irf"] = [0.2, 1.0, 0.2]
        for name in ("a.mat", "b.mat", "c.h5"):
            out[name] = Path(t, name).read_bytes()
    return out


_NPZ = _valid_npz()
_OTHERS = _valid_mat_h5()


@FAST
@given(
    st.lists(st.tuples(st.integers(0, len(_NPZ) - 1), st.integers(0, 255)), max_size=8),
    st.integers(1, len(_NPZ)),
)
def test_load_damaged_npz_data_or_splidar_error(tmp_path_factory, edits, keep):
    """Random bytes changed and the end cut off: the data or a SplidarError."""
    b = bytearray(_NPZ[:keep])
    for pos, val in edits:
        if pos < len(b):
            b[pos] = val
    p = tmp_path_factory.mktemp("dmg") / "c.npz"
    p.write_bytes(bytes(b))
    try:
        cube = load(p)
    except SplidarError:
        return
    assert cube.counts.shape[-1] >= 1


@FAST
@given(
    st.sampled_from(sorted(_OTHERS)),
    st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), max_size=8),
    st.floats(0.05, 1.0),
)
def test_load_damaged_mat_h5_data_or_splidar_error(tmp_path_factory, name, edits, keep):
    """.mat v5 (plain, compressed cells) and .h5 with random damage: data or SplidarError."""
    data = _OTHERS[name]
    b = bytearray(data[: max(int(len(data) * keep), 1)])
    for frac, val in edits:
        b[int(frac * len(b))] = val
    p = tmp_path_factory.mktemp("dmg") / name
    p.write_bytes(bytes(b))
    try:
        cube = load(p, irf_fwhm=2.0)
    except SplidarError:
        return
    assert cube.counts.shape[-1] >= 1


@FAST
@given(
    st.lists(
        st.tuples(
            st.text("abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=8),
            st.tuples(st.integers(0, 10**9), st.integers(0, 10**9)),
            st.sampled_from(["<u2", "<f8", "|O", "<i4", ">u4", "|b1", "<U3"]),
        ),
        min_size=1,
        max_size=3,
    )
)
def test_load_lying_npy_headers_refused_before_allocating(tmp_path_factory, members):
    """Headers claiming any shape and dtype over 16 stored bytes: never a big allocation."""
    p = tmp_path_factory.mktemp("hdr") / "c.npz"
    with zipfile.ZipFile(p, "w") as zf:
        for name, shape, descr in members:
            bio = io.BytesIO()
            hdr = {"descr": descr, "fortran_order": False, "shape": shape}
            np.lib.format.write_array_header_1_0(bio, hdr)
            zf.writestr(f"{name}.npy", bio.getvalue() + bytes(16))
    try:
        load(p, irf_fwhm=2.0)
    except SplidarError:
        return


# ---------------------------------------------------------------------------------------
# detect, reconstruct, process, exports
# ---------------------------------------------------------------------------------------
def _check_points(points: PointSet, n_bins: int, max_surfaces: int, n_classes: int | None):
    d = points.depth_bin
    assert np.all(np.isfinite(d)) and np.all((d >= 0) & (d <= n_bins - 1)), d
    rows, cols = points.image_shape
    assert np.all((points.row >= 0) & (points.row < rows))
    assert np.all((points.col >= 0) & (points.col < cols))
    if len(points):
        per_pixel = np.bincount(points.row * cols + points.col)
        assert per_pixel.max() <= max_surfaces
    if points.intensity is not None:
        assert np.all(np.isfinite(points.intensity)) and np.all(points.intensity >= 0)
    if points.label is not None and n_classes is not None:
        assert np.all((points.label >= 0) & (points.label < n_classes))
    if points.label_confidence is not None:
        conf = points.label_confidence
        assert np.all((conf >= 0) & (conf <= 1)), conf


@SLOW
@given(
    sim=scenes(),
    max_surfaces=st.integers(1, 3),
    pfa=st.sampled_from([1e-4, 1e-3, 1e-2]),
    scales=st.sampled_from([(1,), (1, 3), (1, 3, 7)]),
    n_lib=st.integers(0, 3),
)
def test_process_random_scene_invariants(sim, max_surfaces, pfa, scales, n_lib):
    cube = sim.cube
    library = None
    if n_lib:
        rng = np.random.default_rng(n_lib)
        library = SpectralLibrary(rng.uniform(0.2, 2.0, (n_lib, cube.n_wavelengths)))
    det = splidar.detect(cube, scales=scales, pfa=pfa, max_surfaces=max_surfaces)
    _check_points(det.points, cube.n_bins, max_surfaces, None)
    rec = splidar.reconstruct(det, library=library, max_iter=15)
    _check_points(rec.points, cube.n_bins, max_surfaces, n_lib or 1)
    assert rec.depth_map.shape[:2] == (cube.n_rows, cube.n_cols)


@SLOW
@given(sim=scenes(max_side=6))
def test_exports_random_result_read_back_equal(sim, tmp_path_factory):
    rec = splidar.process(sim.cube, max_iter=20)
    d = tmp_path_factory.mktemp("exp")
    write_npz(rec, d / "result.npz")
    back = read_points(d / "result.npz")
    for name, value in rec.points.to_dict().items():
        np.testing.assert_array_equal(back.to_dict()[name], value, err_msg=name)
    write_csv(rec.points, d / "points.csv")
    csv = read_points(d / "points.csv")
    assert len(csv) == len(rec.points)
    np.testing.assert_array_equal(csv.row, rec.points.row)
    np.testing.assert_array_equal(csv.col, rec.points.col)
    # floats are written with 7 significant digits (float32 precision)
    np.testing.assert_allclose(csv.depth_bin, rec.points.depth_bin, rtol=1e-6)
    if rec.points.intensity is not None and len(rec.points):
        np.testing.assert_allclose(csv.intensity, rec.points.intensity, rtol=1e-6, atol=1e-30)


def test_fuzz_profile_is_bounded():
    """The CI profile stays small; SPLIDAR_FUZZ=release raises it for a release run."""
    if PROFILE == "ci":
        assert FAST.max_examples <= 12 and SLOW.max_examples <= 4
