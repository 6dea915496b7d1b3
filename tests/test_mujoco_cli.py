"""``ivdrem cosim --plant mujoco``: numbers printed and written, imperfections from the
options, bad input refused before anything runs."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from ivdrem.cli import main  # noqa: E402


def test_cosim_mujoco_prints_and_writes_the_numbers(tmp_path, capsys):
    out = tmp_path / "mj.json"
    code = main(["cosim", "--plant", "mujoco", "--t-end", "0.5", "--laws", "iv-drem",
                 "--json", str(out), "--quiet"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "load check (200 states)" in text and "iv-drem" in text
    data = json.loads(out.read_text())
    run, = data["runs"]
    assert run["law"] == "iv-drem" and run["t_end"] == 0.5
    assert run["theta_error_0"] == pytest.approx(np.linalg.norm([1.3, 0.28, 0.32, 0.4, 1.4]))
    assert run["theta_error_ratio"] == pytest.approx(run["theta_error_end"]
                                                     / run["theta_error_0"])
    assert run["plant_us"] > 0 and run["controller_us"] > 0 and run["samples"] == 500
    assert data["load_check"]["M"] < 1e-12 and data["imperfections"]["velocity"] == "exact"


def test_cosim_mujoco_takes_the_robots_imperfections(tmp_path, capsys):
    out = tmp_path / "mj.json"
    code = main(["cosim", "--plant", "mujoco", "--t-end", "0.2", "--laws", "none",
                 "--realistic", "--noise-level", "4", "--tau-rate-limit", "1000",
                 "--encoder-noise", "0.5", "--seed", "3",
                 "--payload-mass", "0.5", "--payload-com", "0.3", "0", "0", "--json", str(out),
                 "--quiet"])
    text = capsys.readouterr().out
    assert code == 0, text
    data = json.loads(out.read_text())
    imp = data["imperfections"]
    assert imp["encoder_counts"] == pytest.approx(2.0 ** 18 / 4)
    assert imp["velocity"] == "difference" and imp["measurement_delay"] == 1
    assert imp["tau_rate_limit"] == [1000.0]
    assert imp["encoder_noise"] == 0.5 and imp["seed"] == 3
    assert "encoder noise σ = 0.5 counts" in text
    assert data["runs"][0]["theta_end"][3] == pytest.approx(0.4 + 0.5 * 0.3)   # θ4 + m_p d
    assert "payload 0.5 kg" in text


@pytest.mark.parametrize("argv, word", [
    (["--laws", "gradient"], "no sampled form"),
    (["--t-end", "-1"], "--t-end"),
    (["--integrator", "rk45"], "invalid choice"),
    (["--payload-mass", "-1"], "payload mass"),
    (["--encoder-counts", "0"], "encoder_counts"),
    (["--encoder-noise", "1"], "needs encoder_counts"),
    (["--comm-step", "0"], "comm-step"),
])
def test_cosim_mujoco_refuses_bad_input(argv, word, capsys):
    code = main(["cosim", "--plant", "mujoco", "--quiet", *argv])
    err = capsys.readouterr().err
    assert code == 2 and word in err, err
    assert "Traceback" not in err


def test_the_robustness_study_runs_every_combination(tmp_path, capsys):
    """noise level × payload × frequency scale × seed × law: one row each, the plot, and
    the varied values applied (the payload's θ, the noise in the run)."""
    import pandas as pd
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 0.2\nlaws = ["iv-drem", "none"]\n'
                     '[model]\nname = "two-link"\n[robustness]\nnoise_levels = [0.0, 10.0]\n'
                     'payload_mass = [0.0, 0.5]\npayload_com = [0.3, 0.0, 0.0]\n'
                     'omega_scale = [1.37]\nseeds = [3]\n', encoding="utf-8")
    out = tmp_path / "out"
    code = main(["cosim", "--plant", "mujoco", "--study", str(study), "--out", str(out),
                 "--quiet"])
    assert code == 0, capsys.readouterr()
    df = pd.read_csv(out / "results.csv")
    assert len(df) == 2 * 2 * 2 and (df["status"] == "ok").all()
    assert (out / "robustness.png").stat().st_size > 10_000 and (out / "study.toml").is_file()
    th4 = df.set_index(["payload_mass", "noise_level", "law"])["theta_error_0"]
    assert th4[(0.5, 0.0, "none")] != th4[(0.0, 0.0, "none")]          # the payload's θ
    a = df[(df.noise_level == 0) & (df.payload_mass == 0) & (df.law == "none")]
    b = df[(df.noise_level == 10) & (df.payload_mass == 0) & (df.law == "none")]
    assert float(a["tracking_rms_last"].iloc[0]) != float(b["tracking_rms_last"].iloc[0])


def test_a_bad_robustness_table_is_refused(tmp_path, capsys):
    study = tmp_path / "s.toml"
    study.write_text('[robustness]\nnoise_level = [1.0]\n', encoding="utf-8")
    code = main(["cosim", "--plant", "mujoco", "--study", str(study), "--out",
                 str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "unknown [robustness] keys ['noise_level']" in err


_STUDY = ('[experiment]\nt_end = 0.2\nlaws = ["iv-drem", "composite-learning"]\n'
          '[model]\nname = "two-link"\n[robustness]\nnoise_levels = [0.0, 1.0]\n'
          'payload_mass = [0.0]\nomega_scale = [1.37]\nseeds = [0]\nmu_max = 60.0\n'
          'gamma = 2e10\n')


def test_ivdrem_study_runs_a_robustness_file_and_writes_its_report(tmp_path, capsys):
    """`ivdrem study FILE` with a [robustness] table: the MuJoCo study, its table, and the
    report (figure, conclusions per noise level) rebuilt equal from results.csv."""
    import pandas as pd

    from ivdrem.plants.study import conclusions, rebuild_report
    study = tmp_path / "s.toml"
    study.write_text(_STUDY, encoding="utf-8")
    out = tmp_path / "out"
    code = main(["study", str(study), "--out", str(out), "--workers", "1", "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    df = pd.read_csv(out / "results.csv")
    assert len(df) == 4 and (df["status"] == "ok").all()
    html = (out / "robustness.html").read_text(encoding="utf-8")
    assert "two-link in MuJoCo" in html and "<svg" in html and "Conclusions" in html
    lines = conclusions(df)
    assert len(lines) == 2 and all("iv-drem" in x and "composite-learning" in x for x in lines)
    assert lines[0] in printed and lines[0] in html.replace("&#x27;", "'")
    # the ratio in the conclusion is the run's own
    row = df[(df.noise_level == 0) & (df.law == "iv-drem")].iloc[0]
    assert f"{row['theta_error_ratio']:.3g}" in lines[0]
    (out / "robustness.html").unlink()
    rebuild_report(out)
    assert (out / "robustness.html").read_text(encoding="utf-8").count("<li>") == 2


def test_seeds_vary_the_runs_that_draw_noise_and_only_those(tmp_path):
    """[robustness] encoder_noise (σ in counts) at the levels > 0 makes the seed matter:
    those levels run once per seed, with different numbers; level 0 (exact) and a study
    without encoder noise run the first seed only."""
    from ivdrem.plants.study import expand, read_robustness, run_one
    study = tmp_path / "s.toml"
    text = ('[experiment]\nt_end = 0.3\nlaws = ["iv-drem"]\n[model]\nname = "two-link"\n'
            '[robustness]\nnoise_levels = [0.0, 10.0]\nseeds = [4, 7]\nmu_max = 60.0\n')
    study.write_text(text + "encoder_noise = 1.0\n", encoding="utf-8")
    experiment, rob, _ = read_robustness(study)
    runs = expand(experiment, rob)
    assert [(r["noise_level"], r["seed"]) for r in runs] == [(0.0, 4), (10.0, 4), (10.0, 7)]
    rows = [run_one(experiment, rob, r) for r in runs[1:]]
    assert all(r["status"] == "ok" for r in rows), rows
    assert rows[0]["tracking_rms_last"] != rows[1]["tracking_rms_last"]
    # seeded; and a worker, given the experiment's configuration, runs the same numbers
    again = run_one(experiment.config, rob, runs[1])
    assert again["tracking_rms_last"] == rows[0]["tracking_rms_last"]
    study.write_text(text, encoding="utf-8")
    experiment, rob, _ = read_robustness(study)
    assert [(r["noise_level"], r["seed"]) for r in expand(experiment, rob)] == \
        [(0.0, 4), (10.0, 4)]
    study.write_text(text + "encoder_noise = -1\n", encoding="utf-8")
    with pytest.raises(ValueError, match="encoder_noise must be"):
        read_robustness(study)


def test_the_studys_gamma_reaches_only_the_laws_with_the_mixing():
    """A number for γ is IV-DREM's and DREM's γ of (21): composite learning keeps its own γ
    of (35) (which multiplies Ψ_b itself; 53.2 there diverges the Panda in 0.4 s); a
    table gives one per law."""
    from ivdrem.plants.study import _law_gamma
    assert _law_gamma(53.2, "iv-drem") == 53.2 and _law_gamma(53.2, "drem") == 53.2
    assert _law_gamma(53.2, "composite-learning") is None and _law_gamma(None, "iv-drem") is None
    g = {"iv-drem": 53.2, "composite-learning": 2.0}
    assert _law_gamma(g, "composite-learning") == 2.0 and _law_gamma(g, "none") is None


@pytest.mark.parametrize("extra, word", [(["--resume"], "--resume is not available"),
                                         (["--scheduler", "tcp://x:1"], "--scheduler")])
def test_ivdrem_study_refuses_what_a_robustness_study_does_not_do(tmp_path, capsys, extra,
                                                                  word):
    study = tmp_path / "s.toml"
    study.write_text(_STUDY, encoding="utf-8")
    code = main(["study", str(study), "--out", str(tmp_path / "o"), "--quiet", *extra])
    err = capsys.readouterr().err
    assert code == 2 and word in err and not (tmp_path / "o").exists()


def test_a_bad_gamma_is_refused(tmp_path, capsys):
    study = tmp_path / "s.toml"
    study.write_text(_STUDY.replace("gamma = 2e10", 'gamma = "big"'), encoding="utf-8")
    code = main(["study", str(study), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "[robustness] gamma must be a number" in err


def test_report_plant_mujoco_gives_the_reports_figures_and_conclusions(tmp_path, capsys):
    """`ivdrem report --plant mujoco`: the paper experiment with the arm in MuJoCo, the
    report (saying so) and C1-C3; its runs are closed_loop's, number for number."""
    from ivdrem.experiments.config import read_config
    from ivdrem.experiments.experiment import Experiment
    from ivdrem.experiments.metrics import signal
    from ivdrem.plants.study import mujoco_paper_run
    from ivdrem.plants.mujoco import closed_loop, controller_kwargs, load
    out = tmp_path / "rep"
    code = main(["report", "--plant", "mujoco", "--t-end", "0.5", "--out", str(out), "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "C1" in printed and "C2" in printed and "C3" in printed
    html = (out / "ivdrem-mujoco.html").read_text(encoding="utf-8")
    assert "MuJoCo" in html and "<svg" in html
    assert (out / "ivdrem-mujoco.pdf").read_bytes().startswith(b"%PDF")
    experiment = Experiment.from_config(read_config(None, {"experiment.t_end": 0.5}))
    run = mujoco_paper_run(experiment)
    kw, start = controller_kwargs(experiment, "iv-drem")
    direct = closed_loop(load("two-link"), 0.5, "iv-drem", every=10, mu_max=135.0, **start,
                         **kw)
    assert np.array_equal(signal(run.runs["iv-drem"].response, "theta_hat"),
                          signal(direct, "theta_hat"))


def test_report_plant_mujoco_refuses_a_law_without_a_sampled_form(tmp_path, capsys):
    code = main(["report", "--plant", "mujoco", "--t-end", "0.5", "--laws", "iv-drem",
                 "not-a-law", "--out", str(tmp_path / "r"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "not-a-law" in err and "Traceback" not in err


def test_the_studys_conclusions_average_over_seeds_and_name_the_diverged():
    """summary_table: the mean over the seeds per law, noise level, payload and disturbance
    scale (scales kept apart: a law diverging at one is not averaged with another), with
    counts; conclusions: each law's numbers, the factor between IV-DREM and the best other
    law, and a law whose runs all failed said to have diverged."""
    import pandas as pd

    from ivdrem.plants.study import conclusions, summary_table
    nan = float("nan")

    def row(law, level, om, seed, ratio=nan, e=nan, d=nan):
        return dict(law=law, noise_level=level, payload_mass=0.0, omega_scale=om, seed=seed,
                    status="failed" if math.isnan(ratio) else "ok", theta_error_ratio=ratio,
                    tracking_rms_last=e, tau_d_error_rms_last=d)
    df = pd.DataFrame([
        row("iv-drem", 1.0, 1.0, 0, 0.01, 1e-3, 0.2), row("iv-drem", 1.0, 1.0, 1, 0.03, 3e-3, 0.4),
        row("iv-drem", 1.0, 1.0, 2),
        row("none", 1.0, 1.0, 0, 0.8, 2e-3, 1.0), row("none", 1.0, 1.0, 1, 0.8, 2e-3, 1.0),
        row("iv-drem", 1.0, 1.37, 0), row("none", 1.0, 1.37, 0, 0.9, 2e-3, 1.0),
        row("iv-drem", 10.0, 1.0, 0), row("none", 10.0, 1.0, 0, 0.9, 5e-3, 2.0)])
    tab = summary_table(df).set_index(["noise_level", "omega_scale", "law"])
    assert tab.loc[(1.0, 1.0, "iv-drem"), "theta_error_ratio"] == pytest.approx(0.02)
    assert tab.loc[(1.0, 1.0, "iv-drem"), ["ok", "failed"]].tolist() == [2, 1]
    assert tab.loc[(1.0, 1.37, "iv-drem"), ["ok", "failed"]].tolist() == [0, 1]
    lines = conclusions(df)
    assert len(lines) == 3
    assert "disturbance frequencies x 1:" in lines[0] and "x 1.37" in lines[1]
    assert "iv-drem ‖θ̃(end)‖/‖θ̃(0)‖ = 0.02" in lines[0] and "0.8" in lines[0]
    assert "40 times smaller than none's" in lines[0] and "(1 run(s) failed)" in lines[0]
    for line in lines[1:]:
        assert "iv-drem diverged in every run" in line and "times" not in line
