"""Tests of the PDF/HTML report and of the `ivdrem report` command (ivdrem.reports).

The simulator is replaced by synthetic runs (ivdrem.reports.synthetic), so these tests
take seconds, not minutes.
"""
import argparse
import re
import shutil
import subprocess
import sys
import types
import zlib

import matplotlib as mpl
import numpy as np
import pytest

from ivdrem.experiments.config import read_config, resolve_config
from ivdrem.experiments.metrics import conclusions, key_numbers
from ivdrem.reports import ReportError, write_report
from ivdrem.reports import figures as report_figures
from ivdrem.cli.report import add_report_arguments, run_report_command
from ivdrem.reports.synthetic import synthetic_paper_run

N_FIGURES = 7  # Figures 1-4 of the paper, θ̂ vs θ, τ, λ_min/μ
N_TEXT_PAGES = 3  # at least: title + conclusions, parameters, errata/solver/versions/FMU check


def text_pages(run):
    """Pages of text (tables) the report of `run` has, rendered on their own."""
    import io
    from matplotlib.backends.backend_pdf import PdfPages
    from ivdrem.reports.content import build_content
    from ivdrem.reports.pdf import write_text_pages
    with mpl.rc_context(report_figures.RC), PdfPages(io.BytesIO()) as pdf:
        titles = [spec.title for spec in report_figures.iter_figures(run)]
        return write_text_pages(pdf, build_content(run, fmu_check=FMU_CHECK), titles)
FMU_CHECK = {"max |q - q_fmu| (rad)": 1.25e-9, "max |dq - dq_fmu| (rad/s)": 3.5e-8, "FMU steps": 60000}


# --------------------------------------------------------------------------- PDF text
def pdf_streams(data: bytes):
    """Decompressed content of every stream of a PDF (Flate or plain)."""
    for m in re.finditer(rb"stream\r?\n", data):
        start = m.end()
        end = data.find(b"endstream", start)
        raw = data[start:end]
        try:
            yield zlib.decompress(raw)
        except zlib.error:
            try:
                yield zlib.decompressobj().decompress(raw)
            except zlib.error:
                yield raw


_PDF_STRING = re.compile(rb"\((?:\\.|[^\\)])*\)")


def _unescape(s: bytes) -> str:
    s = s[1:-1]
    s = re.sub(rb"\\([nrtbf()\\])", lambda m: {b"n": b"\n", b"r": b"\r", b"t": b"\t", b"b": b"\b",
                                               b"f": b"\f"}.get(m.group(1), m.group(1)), s)
    s = re.sub(rb"\\([0-7]{1,3})", lambda m: bytes([int(m.group(1), 8) & 0xFF]), s)
    if len(s) % 2 == 0 and s and s[0::2].count(0) * 2 >= len(s) // 2:
        # two-byte codes (matplotlib's Identity-H TrueType fonts): code = Unicode point
        return s.decode("utf-16-be", "replace")
    return s.decode("latin-1")


def pdf_text_fallback(data: bytes) -> str:
    """Text of the single-byte strings drawn with Tj/TJ in the content streams.

    Enough for ASCII text drawn by matplotlib with TrueType fonts (pdf.fonttype 42):
    pieces of one TJ array are joined, separate text objects separated by a newline.
    """
    out = []
    for stream in pdf_streams(data):
        if b"BT" not in stream:
            continue
        for block in re.findall(rb"BT(.*?)ET", stream, flags=re.S):
            pieces = []
            for arr in re.finditer(rb"\[(.*?)\]\s*TJ|(\((?:\\.|[^\\)])*\))\s*Tj", block, flags=re.S):
                if arr.group(1) is not None:
                    pieces += [_unescape(s) for s in _PDF_STRING.findall(arr.group(1))]
                else:
                    pieces.append(_unescape(arr.group(2)))
            if pieces:
                out.append("".join(pieces))
    return "\n".join(out)


def pdf_page_count(data: bytes) -> int:
    return len(re.findall(rb"/Type\s*/Page(?![s\w])", data))


def pdf_text(path) -> list[str]:
    """Texts of the PDF from every extractor available (the fallback always)."""
    data = path.read_bytes()
    texts = [pdf_text_fallback(data)]
    try:
        import pypdf
        texts.append("\n".join(p.extract_text() or "" for p in pypdf.PdfReader(str(path)).pages))
    except ImportError:
        pass
    if shutil.which("pdftotext"):
        res = subprocess.run(["pdftotext", "-layout", str(path), "-"], capture_output=True, timeout=60)
        if res.returncode == 0:
            texts.append(res.stdout.decode("utf-8", "replace"))
    return texts


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def run():
    return synthetic_paper_run(t_end=60.0, dt=0.02)


@pytest.fixture(scope="module")
def report(run, tmp_path_factory):
    outdir = tmp_path_factory.mktemp("report")
    before = dict(mpl.rcParams)
    html, pdf = write_report(run, outdir, fmu_check=FMU_CHECK)
    return {"outdir": outdir, "html": html, "pdf": pdf, "rc_before": before}


# --------------------------------------------------------------------------- files
def test_both_files_and_nothing_else(report):
    out = report["outdir"]
    assert report["html"] == out / "ivdrem-paper.html"
    assert report["pdf"] == out / "ivdrem-paper.pdf"
    assert sorted(p.name for p in out.iterdir()) == ["ivdrem-paper.html", "ivdrem-paper.pdf"]
    assert report["pdf"].read_bytes().startswith(b"%PDF")
    assert report["html"].stat().st_size < 5_000_000  # decimated curves, not 3000 points a line


def test_global_matplotlib_settings_untouched(report):
    assert dict(mpl.rcParams) == report["rc_before"]


def test_html_has_every_figure_and_table(report, run):
    html = report["html"].read_text("utf-8")
    assert html.startswith("<!DOCTYPE html>")
    assert html.count("<svg") == N_FIGURES + len(run.runs)   # + one Figure D per law
    for k in range(1, N_FIGURES + 1):
        assert f'<figure id="fig{k}"' in html
    for law in run.runs:
        assert f'<figure id="figD-{law}"' in html
        assert f'id="tab-diag-{law}"' in html                      # verdicts of Theorem 2
    for key in ("conclusions", "summary", "parameters", "errata", "solver", "versions", "fmu"):
        assert f'id="tab-{key}"' in html
    for cid in ("C1", "C2", "C3", "C4"):
        assert f"<td>{cid}</td>" in html
    start = html.index('id="tab-conclusions"')
    concl_html = html[start:html.index("</table>", start)]
    assert concl_html.count('class="PASS"') == 3
    assert "KA1" in html and "KA3" in html and "HOLDS" in html
    for c in conclusions(run):
        assert key_numbers(c).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;") in html
    for e in ("E1", "E2", "E3", "E4", "E5"):
        assert f"<td>{e}</td>" in html
    for pkg in ("python", "numpy", "scipy", "control", "numba", "sympy", "matplotlib", "ivdrem"):
        assert f"<td>{pkg}</td>" in html
    assert "git commit" in html
    assert "max |q - q_fmu| (rad)" in html and "1.25e-09" in html
    assert "observer_variant" in html and "[iv_drem]" in html
    assert "Synthetic data" in html


def test_html_is_self_contained(report):
    html = report["html"].read_text("utf-8")
    assert not re.search(r"""(?:src|href)\s*=\s*["']?\s*(?:https?:)?//""", html, flags=re.I)
    assert not re.search(r"<link\b", html, flags=re.I)
    assert not re.search(r"<script\b", html, flags=re.I)
    assert not re.search(r"<img\b", html, flags=re.I)
    assert "@import" not in html and not re.search(r"url\(\s*['\"]?https?:", html)
    assert "<?xml" not in html and "<!DOCTYPE svg" not in html
    # every href points inside the document, ids are unique across the inline SVGs
    ids = re.findall(r'\bid="([^"]+)"', html)
    assert len(ids) == len(set(ids))
    for ref in re.findall(r'href="([^"]*)"', html):
        assert ref.startswith("#") and ref[1:] in ids, ref


def test_pdf_pages_and_text(report, run):
    data = report["pdf"].read_bytes()
    n_text = text_pages(run)
    assert n_text >= N_TEXT_PAGES
    assert pdf_page_count(data) == n_text + N_FIGURES + len(run.runs)
    concl = conclusions(run)
    ratio = f"{concl[2]['measured']['ratio']:.3g}"
    texts = pdf_text(report["pdf"])
    for text in texts:
        flat = re.sub(r"\s+", " ", text)
        assert "Conclusions C1-C3 of the paper and ivdrem's C4" in flat
        for cid in ("C1", "C2", "C3"):
            assert cid in flat
        assert flat.count("PASS") >= 3
        assert ratio in flat
        assert "Errata and choices" in flat and "E5" in flat
        assert "Solver statistics" in flat and "rodas5p" in flat
        assert "Software versions" in flat and "matplotlib" in flat
        assert "FMU check" in flat and "1.25e-09" in flat
        assert "Figure 4. Disturbance estimation error" in flat
    try:
        import pypdf
    except ImportError:
        return
    assert len(pypdf.PdfReader(str(report["pdf"])).pages) == n_text + N_FIGURES + len(run.runs)


def test_pdf_has_no_tex_and_embedded_truetype(report):
    data = report["pdf"].read_bytes()
    assert b"/FontFile2" in data  # TrueType (selectable) fonts
    assert b"/Subtype /Type3" not in data


@pytest.fixture
def text_only(monkeypatch):
    """Reports without figures: the write path is the same, and it takes a second."""
    monkeypatch.setattr(report_figures, "FIGURES", [])


def test_failing_verdicts_are_shown(tmp_path, text_only):
    bad = synthetic_paper_run(t_end=40.0, dt=0.05, iv_converges=False, iv_tau_better=False)
    html, pdf = write_report(bad, tmp_path)
    text = html.read_text("utf-8")
    start = text.index('id="tab-conclusions"')
    concl = text[start:text.index("</table>", start)]
    assert concl.count('class="FAIL"') == 2 and concl.count('class="PASS"') == 1
    assert re.sub(r"\s+", " ", pdf_text(pdf)[0]).count("FAIL") >= 2


def test_figures_of_a_single_law_run():
    run = synthetic_paper_run(t_end=30.0, dt=0.05, laws=["composite-learning"])
    keys = [spec.key for spec in report_figures.iter_figures(run)]
    # no Δ, 𝒲 without a DREM law; the law's Figure D of the diagnostics
    assert keys == ["fig2", "fig3", "fig4", "fig5", "fig6", "fig7", "figD-composite-learning"]
    assert [c["verdict"] for c in conclusions(run)] == [True, None, None, None]


def test_single_law_report_says_not_evaluated(tmp_path, text_only):
    run = synthetic_paper_run(t_end=30.0, dt=0.05, laws=["composite-learning"])
    html, _ = write_report(run, tmp_path)
    assert html.read_text("utf-8").count("not evaluated") >= 2


def test_svg_ids_are_prefixed(run):
    spec = report_figures.fig_tracking_error(run)
    svg = report_figures.figure_to_svg(spec.figure, "figX-")
    ids = re.findall(r'\bid="([^"]+)"', svg)
    assert ids and all(i.startswith("figX-") for i in ids)
    for ref in re.findall(r'href="#([^"]+)"', svg) + re.findall(r"url\(#([^)]+)\)", svg):
        assert ref in ids


def test_decimate_keeps_the_envelope():
    t = np.linspace(0, 100, 200001)
    y = np.sin(40 * t) * np.exp(-t / 50)
    td, yd = report_figures.decimate(t, y, buckets=500)
    assert td.size <= 2 * 500 + 4 and td[0] == t[0] and td[-1] == t[-1]
    assert np.all(np.diff(td) > 0)
    assert yd.max() == y.max() and yd.min() == y.min()


# --------------------------------------------------------------------------- safety
def _fail(*args, **kwargs):
    raise RuntimeError("injected failure while drawing")


def _only(monkeypatch, names):
    monkeypatch.setattr(report_figures, "FIGURES", list(names))


def test_failure_in_a_figure_keeps_previous_report(tmp_path, monkeypatch):
    _only(monkeypatch, ["fig_tracking_error", "fig_tau_d_error"])
    run = synthetic_paper_run(t_end=20.0, dt=0.05)
    html, pdf = write_report(run, tmp_path)
    old_html, old_pdf = html.read_bytes(), pdf.read_bytes()
    monkeypatch.setattr(report_figures, "fig_tau_d_error", _fail)
    with pytest.raises(RuntimeError, match="injected"):
        write_report(synthetic_paper_run(t_end=10.0, dt=0.05), tmp_path)
    assert html.read_bytes() == old_html and pdf.read_bytes() == old_pdf
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ivdrem-paper.html", "ivdrem-paper.pdf"]


def test_failure_while_writing_the_pdf_keeps_previous_report(tmp_path, monkeypatch):
    import ivdrem.reports.report as report_module

    _only(monkeypatch, ["fig_tracking_error"])
    run = synthetic_paper_run(t_end=20.0, dt=0.05)
    html, pdf = write_report(run, tmp_path)
    old_html, old_pdf = html.read_bytes(), pdf.read_bytes()
    real = report_module.write_text_pages

    def half_then_fail(pdf_pages, *args, **kwargs):
        real(pdf_pages, *args, **kwargs)  # some pages are already in the temporary file
        raise OSError("disk full (injected)")

    monkeypatch.setattr(report_module, "write_text_pages", half_then_fail)
    with pytest.raises(OSError, match="injected"):
        write_report(run, tmp_path)
    assert html.read_bytes() == old_html and pdf.read_bytes() == old_pdf
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ivdrem-paper.html", "ivdrem-paper.pdf"]


def test_failure_without_previous_report_leaves_nothing(run, tmp_path, monkeypatch):
    monkeypatch.setattr(report_figures, "fig_theta_hat", _fail)
    with pytest.raises(RuntimeError, match="injected"):
        write_report(run, tmp_path / "new")
    assert list((tmp_path / "new").iterdir()) == []


def test_unrelated_user_file_is_not_overwritten(run, tmp_path):
    mine = tmp_path / "ivdrem-paper.html"
    mine.write_text("<html>my own notes</html>")
    other = tmp_path / "notes.txt"
    other.write_text("keep me")
    with pytest.raises(ReportError, match="not written by ivdrem"):
        write_report(run, tmp_path)
    assert mine.read_text() == "<html>my own notes</html>" and other.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ivdrem-paper.html", "notes.txt"]
    (tmp_path / "ivdrem-paper.html").unlink()
    (tmp_path / "ivdrem-paper.pdf").write_bytes(b"%PDF-1.4 someone else's paper")
    with pytest.raises(ReportError):
        write_report(run, tmp_path)
    assert (tmp_path / "ivdrem-paper.pdf").read_bytes() == b"%PDF-1.4 someone else's paper"
    with pytest.raises(ValueError):
        write_report(run, tmp_path, basename="../escape")


def test_other_basename_overwrite_and_replacing_own_report(run, tmp_path, text_only):
    (tmp_path / "x.html").write_text("scratch")
    html, pdf = write_report(run, tmp_path, basename="x", overwrite=True)
    assert html.name == "x.html" and pdf.name == "x.pdf"
    first = html.read_bytes()
    assert b"scratch" not in first
    later = synthetic_paper_run(t_end=10.0, dt=0.05)
    write_report(later, tmp_path, basename="x")  # our own files: replaced without asking
    assert html.read_bytes() != first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.html", "x.pdf"]


# --------------------------------------------------------------------------- CLI
@pytest.fixture
def fake_paper(monkeypatch):
    """Replace ivdrem.experiments.paper by a module whose run_paper is synthetic."""
    calls = []

    import ivdrem.experiments.paper as real

    def run_paper(experiment, *, laws=None, progress=True, log=None, **kw):
        # the command's Experiment (its configuration resolved once, with its engine)
        calls.append({"config": experiment.config, "laws": laws, "progress": progress,
                      "engine": experiment.engine})
        return synthetic_paper_run(experiment.config, dt=0.05)

    mod = types.ModuleType("ivdrem.experiments.paper")
    mod.run_paper = run_paper
    mod.LawRun, mod.PaperRun = real.LawRun, real.PaperRun
    monkeypatch.setitem(sys.modules, "ivdrem.experiments.paper", mod)
    return calls


def parse(argv):
    return add_report_arguments(argparse.ArgumentParser(prog="ivdrem report")).parse_args(argv)


def test_cli_arguments_defaults():
    a = parse([])
    assert a.config is None and a.out == "reports" and a.t_end is None and a.laws is None
    assert a.quiet is False and a.engine == "compiled"
    with pytest.raises(SystemExit):
        parse(["--engine", "turbo"])


@pytest.fixture
def fake_fmu_check(monkeypatch):
    """The FMU co-simulation check (exercised for real in test_cosim.py), faked."""
    import ivdrem.cli.report as rcli

    class _Cmp:
        def table(self):
            return "signal  H  err  order"

        def verdict(self):
            return "OK: first order"
    rows = {"q, H = 0.001 s": {"max |co-sim − Python|": 3.0e-3, "observed order": ""},
            "q, H = 0.0005 s": {"max |co-sim − Python|": 1.5e-3, "observed order": "1.00"}}
    calls = []

    def fake(config, t_end=10.0, **kw):
        calls.append(t_end)
        return rows, _Cmp()
    monkeypatch.setattr(rcli, "fmu_check", fake)
    return calls


def test_cli_runs_and_writes(fake_paper, fake_fmu_check, tmp_path, capsys, text_only):
    cfg = tmp_path / "my.toml"
    cfg.write_text("[controller]\nK = [3.0, 3.0]\n")
    out = tmp_path / "out"
    args = parse(["--config", str(cfg), "--out", str(out), "--t-end", "30", "--quiet",
                  "--laws", "iv-drem", "composite-learning", "--engine", "reference"])
    assert run_report_command(args) == 0
    (call,) = fake_paper
    assert call["config"]["experiment"]["t_end"] == 30.0
    assert call["config"]["controller"]["K"] == [3.0, 3.0]
    assert call["progress"] is False and call["engine"] == "reference"
    printed = capsys.readouterr().out
    assert str(out / "ivdrem-paper.html") in printed and str(out / "ivdrem-paper.pdf") in printed
    assert "C1" in printed and "C3" in printed and "PASS" in printed
    assert (out / "ivdrem-paper.html").exists() and (out / "ivdrem-paper.pdf").exists()
    assert fake_fmu_check == [10.0]
    html = (out / "ivdrem-paper.html").read_text()
    assert "q, H = 0.0005 s" in html and "1.00" in html


def test_cli_no_fmu_check(fake_paper, fake_fmu_check, tmp_path, text_only):
    args = parse(["--out", str(tmp_path / "o"), "--t-end", "30", "--quiet", "--no-fmu-check"])
    assert run_report_command(args) == 0
    assert fake_fmu_check == []


def test_cli_fmu_check_predicted_to_diverge_is_not_run(fake_paper, tmp_path, capsys, text_only,
                                                       monkeypatch):
    """A configuration whose explicit coupling at the check's 1 ms cannot be stable
    (K = 2000 on the 2-link arm: H lambda_max = 12.6) gets no FMU export and no
    co-simulation; the command says so and why, and the report states it was not run."""
    import ivdrem.fmu as fmu_mod
    import ivdrem.fmu.cosim as cosim_mod

    def refuse(*a, **k):
        raise AssertionError("the FMU check was started")
    monkeypatch.setattr(fmu_mod, "export_fmu", refuse)
    monkeypatch.setattr(cosim_mod, "compare_to_python", refuse)
    cfg = tmp_path / "stiff.toml"
    cfg.write_text("[controller]\nK = [2000.0, 2000.0]\n")
    out = tmp_path / "out"
    assert run_report_command(parse(["--config", str(cfg), "--out", str(out), "--t-end", "30",
                                     "--quiet"])) == 0
    err = capsys.readouterr().err
    assert "ivdrem report: FMU check not run: predicted to diverge" in err
    assert "H lambda_max = 12.6" in err and "--no-fmu-check" in err
    assert "AssertionError" not in err
    html = (out / "ivdrem-paper.html").read_text()
    assert "not run: predicted to diverge" in html and "--no-fmu-check" in html


@pytest.mark.parametrize("text, argv, message", [
    ("[controller]\nKp = [1, 1]\n", [], "did you mean 'controller.K'?"),
    ("", ["--laws", "iv-drem", "composite"], "law 'composite' is not known"),
    ("", ["--t-end", "-5"], "'experiment.t_end' must be > 0"),
])
def test_cli_rejects_bad_config_before_running(fake_paper, tmp_path, capsys, text, argv, message):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    args = parse(["--config", str(cfg), "--out", str(tmp_path / "out"), "--quiet", *argv])
    assert run_report_command(args) == 2
    assert fake_paper == []
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_cli_refuses_unrelated_file_before_running(fake_paper, tmp_path, capsys):
    (tmp_path / "ivdrem-paper.pdf").write_text("not a report")
    assert run_report_command(parse(["--out", str(tmp_path), "--quiet"])) == 2
    assert fake_paper == []
    assert "refusing to overwrite" in capsys.readouterr().err


# --------------------------------------------------------------------------- browser
def _browser():
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


@pytest.mark.skipif(_browser() is None, reason="no chromium to render the HTML")
def test_html_renders_in_a_browser(report, tmp_path):
    png = tmp_path / "page.png"
    cmd = [_browser(), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           "--window-size=1100,2400", f"--screenshot={png}", report["html"].resolve().as_uri()]
    try:
        subprocess.run(cmd, capture_output=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.skip("headless browser did not finish")
    if not png.exists():
        pytest.skip("headless browser wrote no screenshot")
    import matplotlib.image as mimage

    img = mimage.imread(png)[..., :3]
    dark = (img.mean(axis=2) < 0.6).mean()  # text, lines, table rules
    coloured = ((img.max(axis=2) - img.min(axis=2)) > 0.25).mean()  # law colours, verdict cells
    assert img.std() > 0.05
    assert dark > 0.005 and coloured > 0.001


# --------------------------------------------------------------------------- table pagination
def test_table_pages_never_leave_a_lone_row_or_header():
    from ivdrem.reports.pdf import plan_table_pages
    # 10 rows of 1 unit, header 1, pages of 6 units: 5 rows a page -> [5], [5]
    assert plan_table_pages([1] * 10, 1, 6, 6) == (False, [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]])
    # 11 rows: the naive split [5], [5], [1] leaves a lone last row -> [5], [4], [2]
    new, groups = plan_table_pages([1] * 11, 1, 6, 6)
    assert [len(g) for g in groups] == [5, 4, 2] and sum(groups, []) == list(range(11))
    # room for the header and one row only on the current page: the table moves
    new, groups = plan_table_pages([1] * 4, 1, 2.5, 6)
    assert new is True and groups == [[0, 1, 2, 3]]
    # a one-row table may stand alone
    assert plan_table_pages([1], 1, 2.5, 6) == (False, [[0]])
    for n in range(2, 40):
        for first in (1.5, 2.5, 3.5, 6):
            new, groups = plan_table_pages([1] * n, 1, first, 6)
            assert sum(groups, []) == list(range(n))
            assert all(len(g) >= 2 for g in groups), (n, first, groups)


def test_pdf_tables_have_no_lone_rows(tmp_path, text_only):
    """A real report: every table page of the PDF holds at least two rows."""
    import io
    from matplotlib.backends.backend_pdf import PdfPages
    from ivdrem.reports.content import build_content
    from ivdrem.reports.pdf import TextPages, write_text_pages
    run = synthetic_paper_run(t_end=40.0, dt=0.05, laws=["iv-drem", "composite-learning", "drem"])
    seen = {}
    orig = TextPages.flush

    def spy(self):
        seen.update(getattr(self, "rows_per_page", {}))
        return orig(self)
    TextPages.flush = spy
    try:
        with mpl.rc_context(report_figures.RC), PdfPages(io.BytesIO()) as pdf:
            write_text_pages(pdf, build_content(run, fmu_check=FMU_CHECK), [])
    finally:
        TextPages.flush = orig
    assert any(len(p) >= 2 for p in seen.values()), seen             # some table spans pages
    for key, per_page in seen.items():
        assert all(k >= 2 for k in per_page) or per_page == [1], (key, per_page)


def test_fmu_check_takes_the_runs_gamma_auto_instead_of_calibrating_again(monkeypatch):
    """With gamma = "auto" the co-simulation gets the γ the report's IV-DREM run chose
    (calibrating again there ran DP45 at 10 ms steps over 2T: minutes on a real arm), and
    without a run the γ of the rule with the run's own solver (the Experiment's choice)."""
    import ivdrem.diagrams.gamma_auto as gamma_auto
    import ivdrem.fmu as fmu_mod
    import ivdrem.fmu.cosim as cosim_mod
    import ivdrem.cli.report as rcli
    from pathlib import Path

    from ivdrem.experiments.config import closed_loop_kwargs, read_config, resolve_config
    seen = []

    class _Cmp:
        signals, comm_steps, errors, orders = (), (), {}, {}

        def verdict(self):
            return "OK"

    def compare(path, t_end, **kw):
        seen.append(kw["gains"]["gamma"])
        return _Cmp()

    built = []

    def calibrate_gamma(law, model, args, **kw):
        built.append((law, kw["method"]))
        return {"gamma": 77.0}
    monkeypatch.setattr(fmu_mod, "export_fmu", lambda *a, **k: None)
    monkeypatch.setattr(cosim_mod, "compare_to_python", compare)
    monkeypatch.setattr(gamma_auto, "calibrate_gamma", calibrate_gamma)
    config = resolve_config(read_config(Path(__file__).parents[1] / "examples" / "planar3.toml"))[0]
    assert closed_loop_kwargs(config, "iv-drem")["gains"]["gamma"] == "auto"
    rcli.fmu_check(config, 1.0, gamma=50.2)
    assert seen == [50.2] and built == []              # the run's γ, no calibration
    rcli.fmu_check(config, 1.0)
    assert seen == [50.2, 77.0] and built == [("iv-drem", config["solver"]["method"])]
