"""The ranked-candidates table of ``frfcal diagnose`` (frfcal/commands/diagnose.py ``ranked_lines``)."""

from __future__ import annotations

import io

from frfcal.commands.diagnose import print_diagnosis, ranked_lines


def _row(rank, family, grids, parts, size, explained, holdout, checked=True):
    return {"rank": rank, "family": family, "grids": grids, "parts": parts, "center": [0.123, -1.5, 2e-3],
            "size": size, "explained": explained, "explained_holdout": holdout, "checked": checked}


ROWS = [
    _row(1, "shaker_attachment_mass", [18], ["PBAR 3"], "0.654 kg", 0.459, 0.93),
    _row(2, "element_cluster", list(range(101, 112)), ["PSHELL 12", "PSHELL 15", "PSHELL 16"],
         "stiffness factor 0.649", 0.922, None),
    _row(3, "stinger_spring", [18], ["PBAR 3"], "7.24e+04 N/m", 0.031, -0.12, checked=False),
    _row(10, "contact_spring", [40211, 40877], ["PSHELL 2+PSHELL 3", "PSHELL 15"], "4.2e+07 N/m", 0.0, None),
]


def test_columns_stay_aligned_whatever_the_family_name_location_or_size():
    head, *lines = ranked_lines(ROWS)
    # each heading's column: the family and location cells start where their headings start, the numbers end
    # where theirs end
    fam0, loc0 = head.index("family"), head.index("location")
    size1, expl1, hold1 = (head.index(h) + len(h) for h in ("size", "explained", "hold-out"))
    for r, ln in zip(ROWS, lines):
        assert ln.index(r["family"]) == fam0, ln
        assert ln.index("grids ") == loc0, ln
        assert ln[:size1].endswith(r["size"]), ln
        assert ln[:expl1].endswith(f"{100 * r['explained']:.1f}%"), ln
        h = r["explained_holdout"]
        assert ln[:hold1].endswith("-" if h is None else f"{100 * h:.1f}%"), ln
        assert ln.endswith("(linear)") == (not r["checked"])
        assert ln[fam0 + len(r["family"])] == " "  # the longest family is followed by a separator, not cut
    assert "shaker_attachment_mass " in lines[0]
    assert "101 102 103 104..." in lines[1] and "PSHELL 16" not in lines[1]  # 4 grids, 2 parts shown


def test_print_diagnosis_prints_the_aligned_table():
    member = {"member": "all", "articles": ["A1"], "verdict": "effect(s) found", "reason": "r",
              "residual": {"test": "t", "ranked": []}, "nonlinear_modes": [], "ranked": ROWS,
              "candidates": {"shaker_attachment_mass": 1}, "accepted": [], "trials": [],
              "sd": {"calibration_raw": 0.01, "holdout": 0.02, "crossvalidation_rse": None,
                     "residual_all_channels": 0.02, "floor": 0.001, "floor_source": "s", "scatter": 0.0}}
    out = io.StringIO()
    print_diagnosis({"gates": [], "members": [member], "separations": [], "result_file": "x.json"}, out)
    text = out.getvalue().splitlines()
    k = next(i for i, ln in enumerate(text) if ln.lstrip().startswith("# "))
    assert text[k:k + 1 + len(ROWS)] == ranked_lines(ROWS)


def _member_after(label, articles, verdict, **after):
    """A diagnosis.json member with an "after" SD block (its own entries ``after``), nothing ranked or accepted."""
    return {"member": label, "articles": articles, "verdict": verdict, "reason": "r",
            "residual": {"test": "t", "ranked": []}, "nonlinear_modes": [], "ranked": [], "accepted": [],
            "trials": [],
            "sd": {"calibration_raw": 0.01, "holdout": 0.02, "crossvalidation_rse": None,
                   "residual_all_channels": 0.02, "floor": 0.001, "floor_source": "s", "scatter": 0.0,
                   "after": {"calibration_raw": 0.01, "holdout_refined": 0.0125, "holdout_floor_ratio": 1.2,
                             "floor_holdout": 0.0104, "holdout_before_same_footing": 0.02, "holdout": 0.019,
                             "crossvalidation_rse_before": 0.1, "crossvalidation_rse": 0.09,
                             "residual": {"test": "t"}, **after}}}


def test_print_diagnosis_reports_a_negligible_effect_as_dropped():
    z = {"holdout_with": 0.0125, "holdout_without": 0.0125, "ratio": 1.0, "penalty_ratio": 0.9877,
         "max_mode_shift": 0.0, "negligible": True}
    neg = dict(ROWS[2], name="stinger_g18", description="stinger spring at grid 18", size="1e-37 N/m",
               refined_effect=z)
    member = _member_after("all", ["A1"], "no effect accepted", negligible=[neg])
    out = io.StringIO()
    print_diagnosis({"gates": [], "members": [member], "separations": [], "result_file": "x.json"}, out)
    (line,) = [ln for ln in out.getvalue().splitlines() if ln.startswith("NEGLIGIBLE")]
    assert "stinger spring at grid 18" in line and "1e-37 N/m" in line and "x1.0000" in line
    assert not any(ln.startswith("ACCEPTED") for ln in out.getvalue().splitlines())


def test_print_diagnosis_gives_the_refitted_parameters_and_physical_sizes_per_article():
    """Outside data: the deck parameters re-fitted with the accepted effect were only in diagnosis.json, and the
    per-article sizes were printed as normalized c (-0.672 for a stiffness factor 0.328)."""
    from frfcal.campaign._html import _separation_row

    member = _member_after("group2", ["A3", "A4"], "effect(s) found",
                           p_refined={"E_rail": 0.0802, "m_motor": -0.1154})
    sep = {"member": "group2", "name": "cluster_15_K", "family": "element_cluster", "separates": True,
           "separation": {"articles": ["A1", "A3"], "groups": [0, 1], "magnitude": [-0.0021, -0.672],
                          "reason": "gap 0.67"}, "value": [0.9979, 0.3282], "unit": "x"}
    out = io.StringIO()
    print_diagnosis({"gates": [], "members": [member], "separations": [sep], "result_file": "x.json"}, out)
    text = out.getvalue()
    assert "E_rail +8.02 %, m_motor -11.54 %" in text
    assert "A1 0.9979, A3 0.3282 x" in text and "-0.672" not in text
    row = _separation_row(sep)
    assert row[3] == "A1 0.9979 (group 1); A3 0.3282 (group 2)" and row[5] is True


def test_the_ranking_puts_every_singly_recalibrated_place_first_wherever_the_screening_ranked_it():
    """A place tried because it tied with the best point effect (_tied_places) may lie far down the screening's
    order; the reported ranking (by the hold-out SD of the single recalibrations) must still show it."""
    from types import SimpleNamespace as NS

    import numpy as np

    from frfcal.campaign._diagnose import holdout_ranking

    class Term:
        unit = "N/m"

        def value(self, c):
            return 6.2e4 * c

    n = 40
    cands = [NS(name=f"ground_g{k}_z", family="ground_spring", grids=(k,), parts=("PSHELL 2",),
                center=(0.0, 0.02 * k, 0.0), size=0.04, description=f"spring at grid {k}", term=Term())
             for k in range(n)]
    explained = np.linspace(0.2, 0.01, n)  # the screening's order is the grid order
    chk = NS(name="ground_g0_z", c=1.3, explained=0.21, converged=True)
    scr = NS(names=tuple(c.name for c in cands), order=np.arange(n), explained=explained, c_linear=np.ones(n),
             significant=np.ones(n, bool), checks=(chk,), check=lambda name: chk if name == chk.name else None)
    trials = [{"names": ["ground_g0_z"], "holdout_before": 0.028, "holdout_after": 0.00597},
              {"names": ["ground_g33_z"], "holdout_before": 0.028, "holdout_after": 0.00552, "tied_with": "ground_g0_z"},
              {"names": ["ground_g0_z", "ground_g33_z"], "holdout_before": 0.00552, "holdout_after": 0.0055}]
    rows = holdout_ranking(cands, scr, trials, n=10)
    assert [r["name"] for r in rows[:3]] == ["ground_g33_z", "ground_g0_z", "ground_g1_z"]
    assert rows[0]["screening_rank"] == 34 and rows[0]["explained_holdout"] == 1 - 0.00552 / 0.028
    assert rows[2]["explained_holdout"] is None and len(rows) == 10
