"""File size, write time and browser load time of view.html (splidar.view) by point count.

Points: a full image of side x side pixels (a smooth surface with noise), 4 wavelengths
of gamma-distributed intensities and their standard deviations, 3 random labels and
confidences, and 30 % of the pixels with a second layer 80 bins nearer: every colour
mode present and little regularity for gzip beyond the pixel grid (a worst case for the
file size; measured results compress better). Load time: in Debian's headless Chromium
(software WebGL, no GPU) driven by playwright, from navigation to the viewer's ``ready``
(decoding, upload, first frame) as the page's own ``performance.now()``, and the wall
time until ``ready`` seen from Python (including the browser's parsing of the file).

    python benchmarks/bench_view.py            # 1e4, 1e5, 1e6 points
    python benchmarks/bench_view.py --n 1e6 --repeat 3
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from splidar import PointSet
from splidar.view import write_view

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    # WebGL without a GPU: Chromium 150 falls back to SwiftShader by itself; newer
    # versions only when allowed (no effect where the fallback is automatic)
    "--enable-unsafe-swiftshader",
]


def points(n: int, rng) -> PointSet:
    n2 = int(round(n / 1.3))  # pixels; 30 % of them hold a second layer
    side = int(np.ceil(np.sqrt(n2)))
    r, c = np.divmod(np.arange(side * side)[:n2], side)
    extra = rng.choice(n2, n - n2, replace=False)
    row = np.concatenate([r, r[extra]])
    col = np.concatenate([c, c[extra]])
    layer = np.concatenate([np.zeros(n2, int), np.ones(n - n2, int)])
    depth = 300 + 50 * np.sin(row / 60.0) * np.cos(col / 80.0) + rng.normal(0, 0.5, n)
    depth[layer == 1] -= 80
    inten = rng.gamma(4, 3, (n, 4)).astype(np.float32)
    return PointSet(
        row=row,
        col=col,
        depth_bin=depth,
        image_shape=(side, side),
        intensity=inten,
        intensity_std=np.sqrt(inten),
        label=rng.integers(0, 3, n),
        label_confidence=rng.random(n),
        layer=layer,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, nargs="+", default=[1e4, 1e5, 1e6])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    rng = np.random.default_rng(0)
    tmp = Path(tempfile.mkdtemp(prefix="bench-view-"))
    print(f"{'points':>9} {'gzip':>5} {'MB':>6} {'write s':>8} {'ready ms':>9} {'wall s':>7}")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=args.chromium, args=FLAGS, headless=True)
        for n in (int(x) for x in args.n):
            p = points(n, rng)
            for compress in (True, False):
                f = tmp / f"v{n}-{compress}.html"
                writes, readies, walls = [], [], []
                for _ in range(args.repeat):
                    t0 = time.perf_counter()
                    write_view(p, f, compress=compress)
                    writes.append(time.perf_counter() - t0)
                    page = browser.new_page(viewport={"width": 1280, "height": 800})
                    t0 = time.perf_counter()
                    page.goto(f.resolve().as_uri())
                    page.wait_for_function(
                        "() => window.splidarView && window.splidarView.ready", timeout=300_000
                    )
                    walls.append(time.perf_counter() - t0)
                    readies.append(page.evaluate("splidarView.loadMs"))
                    assert page.evaluate("splidarView.drawn") == n
                    page.close()
                print(
                    f"{n:>9} {'yes' if compress else 'no':>5} {f.stat().st_size / 1e6:6.1f} "
                    f"{statistics.median(writes):8.2f} {statistics.median(readies):9.0f} "
                    f"{statistics.median(walls):7.2f}"
                )
        browser.close()


if __name__ == "__main__":
    main()
