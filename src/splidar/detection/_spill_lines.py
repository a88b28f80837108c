"""Spill-over strips beside thin structures, decided on lines of pixels (stage 5a, part 2).

The per-pixel spill-over test (:func:`~splidar.detection._quality.reject_spill_over`)
cannot tell a thin structure's spread from the structure itself at low counts: at 1.6
photons per strand pixel (the net of ``two_layer_scene`` at PPP 4, SBR 0.25) the own
log-ratio of 62 % of the spread candidates is below 0, and of 21 % of the strand's own
(benchmarks/README.md). Both sides pool evidence here, along lines of pixels as long as
the largest box's side (``2 half + 1``), from the raw counts of every pixel on the line
(a pixel the map pass found nothing in counts too).

A kept candidate ``i`` whose pixel holds another kept candidate (a pixel's only
candidate keeps the per-pixel rule: a dim surface's pixels speak weakly either way)
is the spread of the structure through its 4-neighbour ``j`` (a kept candidate at the
same depth, within the IRF's FWHM, in direction ``u`` from ``i``) when, for a return as
bright as the mean own signal of the candidates on ``j``'s line ``P_j`` (through ``j``,
perpendicular to ``u``; the structure the spread would come from), ``i``'s own counts
do not favour the return by ``llr_level`` (a pixel with no return gives such odds with
probability at most ``exp(-llr_level)``; at high counts most surfaces are decided
there, without their lines) and:

1. ``P_j``'s summed own log-likelihood ratio shows the return: ``>= llr_level``;
2. ``i``'s parallel line ``P_i`` rejects it: ``< -llr_level`` (a surface continuing
   through ``i`` alongside ``j``'s would show there);
3. ``i``'s line along ``u``, ``j``'s pixel left out, rejects it, ``< -llr_level``, and
   shows no return of any brightness up to it (the largest log-ratio over a halving
   grid of fractions of it), ``< llr_level``: a structure through ``i`` across
   ``j``'s, such as a strand crossing, or a surface that ends at ``i`` beside a depth
   edge, even one dimmer than ``j``'s (the object seen through a strand, the strand
   taking 40 % of its light), would show there. Beside a thin structure the line holds
   none of its pixels without ``j``: the test is for thin structures (the spread beside
   a wide one is the per-pixel test's);
4. the parallel line beyond ``i`` (through ``i - u``) shows no return of any brightness
   up to it: ``< llr_level`` (a surface enclosed on both sides, such as the object seen
   through a strand between open pixels, or a dim region's boundary row beside a
   bright region at its depth, is not spread).

Each pixel on a line is taken at the depth of its kept candidate nearest the line's
course within the FWHM, else at that course: from ``i``'s depth with the slope of the
opposite neighbours' candidates that interpolate to it (the enclosure test's pairs),
then extrapolated from the last two pixels (a sloped surface keeps its lines, even one
steeper than the FWHM per pixel). The own log-likelihood ratio of a pixel is the
Poisson ratio of a return of ``s`` photons against the background alone over the IRF's
extent, ``sum_t y_t log(1 + s g(t - d) /
b_t) - s sum_t g(t - d)`` with ``b = max(spatial + dev, 0)`` (``eq:background_3``).
At even odds (``llr_level`` 0) a noisy line decides by chance; ``detect`` passes
``PRESENCE_LLR`` (odds of 20:1 each way, the presence test's level). All candidates are
decided on the same kept set (one pass: a rejection does not change another's lines
beyond the depth a pixel is taken at).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ._kernels import _interp_irf
from ._quality import _by_pixel
from ._slopes import _row_bands, _split

__all__ = ["SpillLines", "reject_spill_lines"]

#: "A return of any brightness up to the structure's": the fractions 1, 1/2, ..., 1/16
#: of it (a halving grid over the range where a line of pixels can show a return: at
#: 1/16 of a strand's 1.6 photons, 11 pixels hold about one photon)
_N_FRACTIONS = 5
#: the 4-neighbour directions (row, col) in which a candidate's source ``j`` is sought
_DIRS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]], np.int64)


@dataclass(frozen=True)
class SpillLines:
    """What the line test decided.

    Attributes
    ----------
    rejected : ndarray (S,), bool
        The candidates that are a structure's spread.
    support : ndarray (S,), bool
        The kept candidates at a rejected spread's depth among its 8 neighbours: the
        spread is not a surface of its pixel, but the return the pooled scales saw there
        is theirs, so its removal must not take that support from them (the isolated
        test, stage 5b, counts them as shared).
    """

    rejected: np.ndarray
    support: np.ndarray


def reject_spill_lines(
    surf: dict,
    keep: np.ndarray,
    counts,
    *,
    spatial: np.ndarray,
    dev: np.ndarray,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    half: int,
    llr_level: float,
    n_jobs: int = 1,
) -> SpillLines:
    """Kept candidates that are the spread of a structure beside them, on lines of pixels.

    Parameters
    ----------
    surf : dict
        Candidate table: ``row``, ``col`` (S,) int, ``depth_bin`` (S,) float (bins),
        ``own_counts`` (S, L, W) int and ``own_background`` (S, L, W) float (the
        pixel's counts and ``bhat`` over the candidate's window, zero outside its
        support), ``image_shape`` (R, C).
    keep : (S,) bool
        Candidates kept so far; the others are neither tested nor on any line.
    counts : array_like (R, C, L, T) int
        Raw counts (a lazy cube is read by bands of rows where candidates are tested).
    spatial : (R, C, L) float
        Background level ``b_{n,l}`` (``eq:background_2``).
    dev : (L, T) float
        ``bbar_{l,t} - mean_t bbar_{l,t}`` (``eq:background_3``).
    irf : (L, n) float
        Normalised IRF.
    peak : (L,) int
        Sample of each IRF's peak (the depth reference).
    fwhm : float
        Same-depth tolerance (bins).
    half : int
        Half-length of the lines (pixels): ``max k // 2``, the largest box's reach.
    llr_level : float
        Natural-log likelihood ratio at which a line shows (``>= llr_level``) or rejects
        (``< -llr_level``) the return (module docstring).
    n_jobs : int
        Threads (the candidates are decided independently: the result does not depend
        on it).

    Returns
    -------
    SpillLines
        ``rejected`` (always False where ``keep`` is False) and ``support``.

    Examples
    --------
    A bright vertical strand (column 2) with a background candidate in every pixel and
    spread candidates at its depth in column 3:

    >>> import numpy as np
    >>> from splidar.irf import gaussian_irf
    >>> g = np.asarray(gaussian_irf(3.0), float)[None]
    >>> pk = np.array([int(g.argmax())])
    >>> R, C, T, W = 9, 6, 60, 13
    >>> y = np.zeros((R, C, 1, T), np.int32)
    >>> y[:, 2, 0, 19:22] = [1, 3, 1]  # the strand's return peaks on bin 20
    >>> rows, cols, deps = [], [], []
    >>> for r in range(R):
    ...     rows += [r, r, r]; cols += [2, 3, 3]; deps += [20.0, 20.0, 45.0]
    ...     y[r, 3, 0, 44:47] = [1, 3, 1]  # column 3's own surface, behind
    >>> S = len(rows)
    >>> own = np.zeros((S, 1, W), np.int32); own[::3, 0, 5:8] = [1, 3, 1]
    >>> surf = dict(row=np.array(rows), col=np.array(cols), depth_bin=np.array(deps),
    ...             own_counts=own, own_background=np.full((S, 1, W), 0.05, np.float32),
    ...             image_shape=(R, C))
    >>> res = reject_spill_lines(surf, np.ones(S, bool), y, spatial=np.full((R, C, 1), 0.05),
    ...                          dev=np.zeros((1, T)), irf=g, peak=pk, fwhm=3.0, half=3,
    ...                          llr_level=3.0)
    >>> rej = res.rejected
    >>> rej[1::3].tolist() == [True] * R, bool(rej[0::3].any() or rej[2::3].any())
    (True, False)
    >>> bool(res.support[0::3].all())  # the strand: its spread's source
    True
    """
    R, C = (int(v) for v in surf["image_shape"])
    rej = np.zeros(keep.size, bool)
    sup = np.zeros(keep.size, bool)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return SpillLines(rej, sup)
    row = np.asarray(surf["row"], np.int64)[idx]
    col = np.asarray(surf["col"], np.int64)[idx]
    depth = np.asarray(surf["depth_bin"], np.float64)[idx]
    # the own signal (S, L) summed over the windows, then taken: no copy of the windows
    cnt = np.asarray(surf["own_counts"]).sum(axis=-1, dtype=np.float64)
    own = cnt[idx] - _row_sums(surf["own_background"], idx)
    own = np.maximum(own, 0.0)
    del cnt
    pix = row * C + col
    order, starts = _by_pixel(row, col, (R, C))
    n_pix = np.diff(starts)[pix]
    test = np.flatnonzero(n_pix > 1)  # crowded pixels only
    if test.size == 0:
        return SpillLines(rej, sup)
    out = np.zeros(idx.size, np.bool_)
    src = np.zeros(idx.size, np.bool_)
    irf = np.ascontiguousarray(irf, np.float64)
    pk = np.ascontiguousarray(peak, np.float64)
    sp = np.asarray(spatial, np.float32)
    dv = np.ascontiguousarray(dev, np.float64)
    h = int(half)
    for sel, y, y0 in _row_bands(counts, row[test], h + 1, cols=col[test]):
        part = test[sel]

        def run(a, b, part=part, y=y, y0=y0):
            _lines_kernel(
                part[a:b], row, col, depth, own, order, starts, R, C, y, int(y0), sp, dv,
                irf, pk, float(fwhm), h, float(llr_level), out, src,
            )  # fmt: skip

        _split(part.size, n_jobs, run)
    rej[idx] = out
    sup[idx] = src & ~out
    return SpillLines(rej, sup)


@njit(cache=True, nogil=True)
def _pixel_llr(y, yr, c, sp, dev, irf, peak, d, s):
    """Own log-likelihood ratio of a return of ``s`` (L,) photons at depth ``d`` (bins)
    in the raw counts ``y[yr, c]`` (L, T) against ``max(sp[l] + dev[l, t], 0)``, over the
    IRF's extent. The IRF's interpolation is evaluated at the bins holding photons only:
    its sum over the extent is ``sum(g) - (1 - f) g[-1] - f g[0]`` for a shift of
    fractional part ``f`` when the window does not cut it (linear interpolation)."""
    L = y.shape[2]
    T = y.shape[3]
    n = irf.shape[1]
    out = 0.0
    for l in range(L):
        sl = max(s[l], 1e-9)
        lo = int(np.ceil(d - peak[l]))
        hi = int(np.floor(d - peak[l])) + n
        t0 = max(lo, 0)
        t1 = min(hi, T)
        if t0 == lo and t1 == hi:
            f = lo - (d - peak[l])  # the first sample's position in the IRF, in [0, 1)
            gsum = 0.0
            for i in range(n):
                gsum += irf[l, i]
            if f > 0.0:
                gsum -= (1.0 - f) * irf[l, n - 1] + f * irf[l, 0]
            out -= sl * gsum
            for t in range(t0, t1):
                v = y[yr, c, l, t]
                if v != 0:
                    g = _interp_irf(irf[l], t - d + peak[l])
                    b = max(np.float64(sp[l]) + dev[l, t], 1e-9)
                    out += v * np.log1p(sl * g / b)
            continue
        for t in range(t0, t1):
            g = _interp_irf(irf[l], t - d + peak[l])
            out -= sl * g
            v = y[yr, c, l, t]
            if v != 0:
                b = max(np.float64(sp[l]) + dev[l, t], 1e-9)
                out += v * np.log1p(sl * g / b)
    return out


@njit(cache=True, nogil=True)
def _depth_at(p, d, depth, order, starts, fwhm):
    """The depth of pixel ``p``'s candidate nearest ``d`` within ``fwhm``, else ``d``."""
    best = d
    gap = fwhm
    for k in range(starts[p], starts[p + 1]):
        e = depth[order[k]]
        if abs(e - d) <= gap:
            gap = abs(e - d)
            best = e
    return best


@njit(cache=True, nogil=True)
def _slope_at(r0, c0, ur, uc, d, depth, order, starts, R, C, fwhm):
    """Depth change per pixel along ``(ur, uc)`` at ``(r0, c0)``: half the difference of
    the opposite neighbours' candidates whose mean is nearest ``d`` within ``fwhm`` (the
    enclosure test's interpolation, ``docs/detection.md``), else 0."""
    ra, ca, rb, cb = r0 - ur, c0 - uc, r0 + ur, c0 + uc
    if ra < 0 or ra >= R or ca < 0 or ca >= C or rb < 0 or rb >= R or cb < 0 or cb >= C:
        return 0.0
    pa = ra * C + ca
    pb = rb * C + cb
    best = fwhm
    slope = 0.0
    for ka in range(starts[pa], starts[pa + 1]):
        da = depth[order[ka]]
        for kb in range(starts[pb], starts[pb + 1]):
            db = depth[order[kb]]
            gap = abs(0.5 * (da + db) - d)
            if gap <= best:
                best = gap
                slope = 0.5 * (db - da)
    return slope


@njit(cache=True, nogil=True)
def _line(r0, c0, ur, uc, skip, d, s, a, floor=np.inf):
    """Summed own log-likelihood ratio over the pixels ``(r0, c0) + k (ur, uc)``, ``|k| <=
    h``, ``k != skip``, inside the image; ``a`` = ``(depth, order, starts, R, C, y, y0,
    sp, dev, irf, peak, fwhm, h)``. Each pixel is taken at the depth of its candidate
    nearest the line's course within ``fwhm``, else at that course: from ``d`` at ``k =
    0`` with the slope of :func:`_slope_at`, then extrapolated from the last two pixels'
    depths (a sloped surface is followed). Returns early, with a partial sum ``>=
    floor``, once the pixels left cannot take it below ``floor`` (a pixel's ratio is at
    least ``-sum(s)``: the IRF sums to 1): for callers that compare with ``floor``."""
    depth, order, starts, R, C, y, y0, sp, dev, irf, peak, fwhm, h = a
    slope0 = _slope_at(r0, c0, ur, uc, d, depth, order, starts, R, C, fwhm)
    s_sum = 0.0
    for v in s:
        s_sum += max(v, 1e-9)
    left = 2 * h + 1
    tot = 0.0
    for sgn in (1, -1):
        prev = d
        slope = sgn * slope0
        for m in range(0 if sgn == 1 else 1, h + 1):
            k = sgn * m
            r = r0 + k * ur
            c = c0 + k * uc
            if r < 0 or r >= R or c < 0 or c >= C:
                break
            e = _depth_at(r * C + c, prev + (slope if m > 0 else 0.0), depth, order, starts, fwhm)
            if m > 0:
                slope = e - prev
            prev = e
            if k != skip:
                tot += _pixel_llr(y, r - y0, c, sp[r, c], dev, irf, peak, e, s)
                left -= 1
                if tot - left * s_sum >= floor:
                    return tot
    return tot


@njit(cache=True, nogil=True)
def _line_any(r0, c0, ur, uc, skip, d, s, a, level, whole=np.nan):
    """Whether :func:`_line`'s largest value for a return of any brightness up to ``s``,
    over the fractions 1, 1/2, ..., of it (:data:`_N_FRACTIONS`), reaches ``level``.
    Stops at the first fraction that does (the largest value is then ``>= level``
    whatever the others give). ``whole``: the line's value at fraction 1 when the
    caller has it (a :func:`_line` call at ``s`` that returned below its floor: the
    whole sum, to the bit), else NaN (computed)."""
    f = 1.0
    for k in range(_N_FRACTIONS):
        v = whole if k == 0 and not np.isnan(whole) else _line(r0, c0, ur, uc, skip, d, s * f, a)
        if v >= level:
            return True
        f *= 0.5
    return False


@njit(cache=True, nogil=True)
def _lines_kernel(
    test, row, col, depth, own, order, starts, R, C, y, y0, sp, dev, irf, peak, fwhm, h,
    level, out, src,
):  # fmt: skip
    """The test of :func:`reject_spill_lines` for the candidates ``test`` (rows of the
    kept table); ``y`` holds image rows from ``y0``. ``out`` marks the spread, ``src``
    the same-depth candidates among a rejected one's 8 neighbours (threads on parts of
    ``test`` may both set an element of ``src``: to the same value)."""
    L = own.shape[1]
    s = np.empty(L, np.float64)
    for i in test:
        r = row[i]
        c = col[i]
        d = depth[i]
        for q in range(4):
            dr = _DIRS[q, 0]
            dc = _DIRS[q, 1]
            rj = r + dr
            cj = c + dc
            if rj < 0 or rj >= R or cj < 0 or cj >= C:
                continue
            pj = rj * C + cj
            found = False
            for k in range(starts[pj], starts[pj + 1]):
                if abs(depth[order[k]] - d) <= fwhm:
                    found = True
            if not found:
                continue
            ur = dc  # perpendicular to (dr, dc)
            uc = dr
            # s: the mean own signal of the same-depth candidates on j's line
            s[:] = 0.0
            n = 0
            for k in range(-h, h + 1):
                rr = rj + k * ur
                cc = cj + k * uc
                if rr < 0 or rr >= R or cc < 0 or cc >= C:
                    continue
                p = rr * C + cc
                for kk in range(starts[p], starts[p + 1]):
                    jj = order[kk]
                    if abs(depth[jj] - d) <= fwhm:
                        s += own[jj]
                        n += 1
            s /= max(n, 1)
            # 0. i's own counts favour the return at the level: they decide (a pixel with
            # no return gives such odds with probability at most exp(-level))
            if _pixel_llr(y, r - y0, c, sp[r, c], dev, irf, peak, d, s) >= level:
                continue
            a = (depth, order, starts, R, C, y, y0, sp, dev, irf, peak, fwhm, h)
            # 2. i's parallel line rejects the return
            if _line(r, c, ur, uc, h + 1, d, s, a, -level) >= -level:
                continue
            # 3. so does the line along (dr, dc) through i, j's pixel (k = 1) left out,
            # and it shows no fainter return
            across = _line(r, c, dr, dc, 1, d, s, a, -level)
            if across >= -level:
                continue
            # (below its floor, ``across`` is the whole sum: fraction 1 of the next test)
            if _line_any(r, c, dr, dc, 1, d, s, a, level, across):
                continue
            if _line(rj, cj, ur, uc, h + 1, d, s, a) < level:
                continue  # 1. j's line does not show the return
            rf = r - dr
            cf = c - dc
            if 0 <= rf < R and 0 <= cf < C and _line_any(rf, cf, ur, uc, h + 1, d, s, a, level):
                continue  # 4. enclosed by a surface on both sides
            out[i] = True
            for rr in range(max(r - 1, 0), min(r + 2, R)):
                for cc in range(max(c - 1, 0), min(c + 2, C)):
                    p = rr * C + cc
                    for k in range(starts[p], starts[p + 1]):
                        if abs(depth[order[k]] - d) <= fwhm:
                            src[order[k]] = True
            break


def _row_sums(windows, idx) -> np.ndarray:
    """``windows[idx].sum(axis=-1, dtype=float64)``, ``(idx.size, L)``: the rows read
    a part at a time (an :class:`~splidar.detection._windows.OwnBackground` computes the
    rows it is given only; each row summed as in the whole array)."""
    L = int(windows.shape[1])
    out = np.empty((idx.size, L), np.float64)
    step = max(1, 2**25 // (4 * L * max(int(windows.shape[-1]), 1)))
    for a in range(0, idx.size, step):
        out[a : a + step] = np.asarray(windows[idx[a : a + step]]).sum(axis=-1, dtype=np.float64)
    return out
