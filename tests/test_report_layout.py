"""Layout of the report's text pages: measured wrapping, readable tables."""
import numpy as np
import pytest

from ivdrem.reports.pdf import _width_in, _wrap


@pytest.mark.parametrize("bold", [False, True])
def test_wrapped_lines_fit_their_column(bold):
    """Every line _wrap returns is no wider than the column, measured with the font that
    draws it (bold headers are wider than an average glyph width assumed: they collided)."""
    rng = np.random.default_rng(3)
    words = ["KA3", "normalised", "mean", "shared", "frequency", "with", "τ_d", "‖𝒲‖/|Δ|,",
             "last", "window", "‖θ̃(t_end)‖", "composite-learning", "supercalifragilisticexpialidocious"]
    for _ in range(200):
        text = " ".join(rng.choice(words, size=rng.integers(1, 12)))
        width = float(rng.uniform(0.5, 2.5))
        size = float(rng.choice([7.5, 8.0, 9.0]))
        lines = _wrap(text, width, size, bold)
        assert " ".join(lines).split() == text.split() or "".join(lines).replace(" ", "") \
            == text.replace(" ", "")              # nothing lost (long words may be broken)
        for ln in lines:
            assert len(ln) <= 1 or _width_in(ln, size, bold) <= width + 1e-9, (ln, width)


def test_bold_is_measured_wider():
    s = "KA3 normalised mean"
    assert _width_in(s, 8, True) > _width_in(s, 8, False) > 0


def test_tables_name_what_they_measure():
    from ivdrem.reports.content import build_content
    from ivdrem.reports.synthetic import synthetic_paper_run
    from ivdrem.reports.content import measured_label
    run = synthetic_paper_run(dt=0.05)
    content = build_content(run)
    tables = {t.key: t for t in content.tables}
    assert tables["conclusions"].title == "Conclusions C1-C3 of the paper and ivdrem's C4, measured"
    solver = tables["solver"]
    assert "integration (s)" in solver.header and "compile + load (s)" in solver.header
    from ivdrem.experiments.diagnostics import diagnose_run
    diags = diagnose_run(run)
    shown = 0
    for law, d in diags.items():
        t = tables[f"diag-{law}"]
        for row, check in zip(t.rows, d["checks"]):
            assert row[0] == check["id"]
            for k, v in check["measured"].items():
                if isinstance(v, (list, dict)) or "_" not in k:
                    continue
                if f"{measured_label(k)} =" in row[2]:
                    shown += 1
                assert f"{k} =" not in row[2], (law, check["id"], row[2])
    assert shown > 20


def test_laws_are_told_apart_by_colour_and_line():
    """IV-DREM and DREM, σ-modification and "none" had nearly the same colours; every
    registered law now has its own Okabe-Ito colour, and laws of nearly the same grey differ
    in line style too (tests/test_law_suite.py checks the grey rule for every law)."""
    from ivdrem.laws import law_names
    from ivdrem.reports.figures import law_color
    colours = [law_color(law) for law in law_names()]
    assert len(set(colours)) == len(colours)
    okabe_ito = {"#E69F00", "#56B4E9", "#009E73", "#F0E442", "#0072B2", "#D55E00", "#CC79A7",
                 "#000000"}
    assert set(colours) <= okabe_ito
