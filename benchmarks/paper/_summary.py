"""``summary.md``: the paper's numbers beside ours, as Markdown tables."""

from __future__ import annotations


def _pct(x) -> str:
    return "-" if x is None else f"{x:.1f}"


def _simulated(part: dict) -> list[str]:
    sc = part["scene"]
    out = [
        f"## 1. Simulated two-layer scene ({sc['name']}, {sc['shape'][0]} x {sc['shape'][1]}, "
        f"T = {sc['n_bins']}, tau = {part['tau_mm']:g} mm)",
        "",
        "The paper shows this experiment as plots only (no numbers). Ours:",
        "",
        "| background | PPP | SBR | method | F_true | F_false | DAE (mm) | IAE / mean | label "
        "acc. |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in part["rows"]:
        lab = "-" if r["label_accuracy"] is None else f"{r['label_accuracy']:.3f}"
        dae = "-" if r["dae_mm"] is None else f"{r['dae_mm']:.2f}"
        iae = "-" if r["iae_rel"] is None else f"{r['iae_rel']:.3f}"
        out.append(
            f"| {r['background']} | {r['ppp']:g} | {r['sbr']:g} | {r['method']} | "
            f"{r['f_true']:.3f} | {r['f_false']} | {dae} | {iae} | {lab} |"
        )
    out += ["", "The paper's statements about its plots, checked on splidar's rows:", ""]
    for c in part["paper_claims"].values():
        verdict = {True: "holds", False: "does not hold", None: "untested"}[c["holds_for_splidar"]]
        out.append(f'- "{c["paper"]}": **{verdict}** ({c["evidence"]})')
    return out


def _acquisition(part: dict) -> list[str]:
    paper = part["paper"]
    out = [
        "## 2. Detection accuracy against acquisition time",
        "",
        f"Paper: {paper['source']}; PPP = {paper['ppp_per_ms']:g} x ms "
        f"({paper['ppp_note']}). Ours: simulated object scene "
        f"{part['scene']['shape'][0]} x {part['scene']['shape'][1]}, SBR "
        f"{part['scene']['sbr']:g}. Accuracy in % of pixels.",
        "",
        "| ms | PPP | paper MSTD | paper MSTD + TV | paper proposed | splidar | per-pixel | "
        "coarse-7 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in part["side_by_side"]:
        p, o = e["paper_pct"], e["ours_pct"]
        out.append(
            f"| {e['acquisition_ms']:g} | {e['ppp']:g} | {p['MSTD']} | {p['MSTD + TV']} | "
            f"{p['Proposed']} | {_pct(o.get('splidar'))} | {_pct(o.get('per-pixel'))} | "
            f"{_pct(o.get('coarse-7'))} |"
        )
    return out


def _face(part: dict) -> list[str]:
    if "skipped" in part:
        return ["## 3. Real face at shorter acquisitions", "", f"Skipped: {part['skipped']}."]
    d = part["data"]
    out = [
        "## 3. Real face at shorter acquisitions",
        "",
        f"Ours: the mannequin face ({d['shape'][0]} x {d['shape'][1]}, T = {d['n_bins']}), "
        f"photons thinned, each method against its own result on all photons, tau = "
        f"{d['tau_bins']:.2f} bins. Paper: {part['paper']['source']} (a different scene).",
        "",
        "| fraction | method | F_true % | F_false | IAE | IAE / mean | detection acc. % |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in part["rows"]:
        iae = "-" if r["iae"] is None else f"{r['iae']:.3f}"
        rel = "-" if r["iae_rel"] is None else f"{r['iae_rel']:.3f}"
        out.append(
            f"| {r['fraction']:.4g} | {r['method']} | {100 * r['f_true']:.1f} | "
            f"{r['f_false']} | {iae} | {rel} | {100 * r['detection_accuracy']:.1f} |"
        )
    for e in part["side_by_side"]:
        p = e["paper"]
        out.append("")
        out.append(
            f"Paper at {e['paper_acquisition_ms']:g} ms (fraction {e['fraction']:.4g}): "
            + "; ".join(
                f"{m} F_true {p['F_true_pct'][m]} %, F_false {p['F_false'][m]}, IAE {p['IAE'][m]}"
                for m in p["F_true_pct"]
            )
        )
    return out


def summary_markdown(results: dict) -> str:
    """The side-by-side tables of ``results.json`` as Markdown."""
    meta = results["meta"]
    lines = [
        "# The paper's experiments: ours beside the paper's",
        "",
        f"splidar {meta['splidar']}, {'quick' if meta['quick'] else 'full'} run, seed "
        f"{meta['seed']}, {meta['seconds']:.0f} s. Figures in `figures/`, every number in "
        "`results.json`.",
        "",
    ]
    for key, fn in (("simulated", _simulated), ("acquisition", _acquisition), ("face", _face)):
        part = results.get(key, {})
        if "skipped" in part and key != "face":
            lines += [f"## {key}: skipped ({part['skipped']})", ""]
            continue
        lines += [*fn(part), ""]
    red = results["data_reduction"]["runs"]
    if red:
        lines += [
            "## 4. Data reduction",
            "",
            "The paper claims a significant reduction without a number. Ours (splidar's 3D map):",
            "",
            "| run | voxels kept % | photons in them % |",
            "|---|---|---|",
            *(
                f"| {e['run']} | {100 * e['voxel_fraction']:.2f} | "
                f"{100 * e['photon_fraction']:.1f} |"
                for e in red
            ),
            "",
        ]
    return "\n".join(lines)
