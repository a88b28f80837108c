"""The numbers and claims of Belmekki et al. that the paper run is compared with.

Read from the paper's LaTeX source (``/work/shared/paper``): its two tables are copied
verbatim; its figures (the Art experiment, data reduction) carry no numbers, only
statements, which are quoted and checked against our measurements in ``run.py``.
"""

from __future__ import annotations

#: Table ``tabl:AccTD``: target detection accuracy (%) on the Lego figurine scene
#: (200 x 200 pixels, L = 4 wavelengths, T = 1500 bins of 2 ps, SBR 1.3, K = 3 classes)
#: against the acquisition time per pixel. Not public: compared with a simulated scene
#: of the same make (one multispectral object in front of empty pixels, SBR 1.3).
ACC_TD = {
    "source": "Table tabl:AccTD (Lego figurine, 200 x 200, L = 4, T = 1500, SBR 1.3)",
    "acquisition_ms": [0.4, 2.0, 4.0, 20.0, 40.0, 80.0],
    "accuracy_pct": {
        "MSTD": [73.8, 87.7, 93.3, 97.9, 98.2, 98.2],
        "MSTD + TV": [94.1, 95.2, 95.7, 98.2, 98.3, 98.2],
        "Proposed": [93.3, 98.5, 98.7, 98.6, 98.9, 100.0],
    },
    # "a Lego figurine with 2ms acquisition time per-pixel (PPP ~ 50)": 25 photons per ms
    "ppp_per_ms": 25.0,
    "ppp_note": "PPP from the caption of fig:Target_detection_one_surface (2 ms ~ PPP 50), "
    "assumed proportional to the acquisition time",
}

#: Table ``tabl:table_TD``: man behind camouflage (159 x 78 pixels, T = 600, two surfaces
#: in places), tau = 1 cm, reference = the proposed method's result at 3.2 ms per pixel.
#: Not public: compared with the mannequin face thinned to the same fractions of its full
#: acquisition (0.5 / 3.2 and 1 / 3.2), reference = splidar on all its photons.
TABLE_TD = {
    "source": "Table tabl:table_TD (man behind camouflage, 159 x 78, T = 600, tau = 1 cm, "
    "reference: the proposed method at 3.2 ms)",
    "acquisition_ms": [0.5, 1.0],
    "fraction_of_reference": [0.5 / 3.2, 1.0 / 3.2],
    "IAE": {"Proposed": [17.72, 14.51], "MuSaPoP": [20.45, 16.63], "RT3D": [21.45, 17.78]},
    "F_true_pct": {"Proposed": [91.7, 94.5], "MuSaPoP": [74.3, 87.1], "RT3D": [81.6, 83.6]},
    "F_false": {"Proposed": [243, 129], "MuSaPoP": [81, 209], "RT3D": [442, 254]},
    "ppp_note": "7 to 44.6 photons per pixel for 0.5 to 3.2 ms, of which 2.1-13.3 background",
}

#: The Art experiment (``fig:3D_reconst_Art``, ``fig:Quant_3D_Art``): plots only. Its
#: statements, each checked on our grid by ``run.py`` (key -> quoted claim).
ART_CLAIMS = {
    "improves_with_ppp": "the performance improves for larger PPP and/or SBR",
    "more_sensitive_to_ppp": "the overall performance are more sensitive to a decrease in "
    "PPP than in SBR",
    "false_worse_with_sbr_at_low_ppp": "false detection gets worse if the SBR level increases "
    "for low PPP levels",
    "nonuniform_slightly_lower_at_low_ppp": "slightly lower performance can be observed for "
    "non-uniform background at low PPP levels",
}
ART_SETUP = {
    "source": "section Evaluation on simulated data; figures without numbers",
    "shape": [185, 232],
    "n_bins": 164,
    "tau_mm": 4.0,
    "scales": [1, 5, 7, 11],
    "ppp_sbr": "two values of PPP and SBR (not given)",
}

#: Data reduction: claimed, never quantified.
DATA_REDUCTION = {
    "claim": "a multiscale approach for 3D surface detection ... to permit a significant "
    "reduction in data volume",
    "numbers": None,
}
