"""``ivdrem cosim --plant mujoco``: numbers printed and written, imperfections from the
options, bad input refused before anything runs."""
from __future__ import annotations

import json

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
                 "--payload-mass", "0.5", "--payload-com", "0.3", "0", "0", "--json", str(out),
                 "--quiet"])
    text = capsys.readouterr().out
    assert code == 0, text
    data = json.loads(out.read_text())
    imp = data["imperfections"]
    assert imp["encoder_counts"] == pytest.approx(2.0 ** 18 / 4)
    assert imp["velocity"] == "difference" and imp["measurement_delay"] == 1
    assert imp["tau_rate_limit"] == [1000.0]
    assert data["runs"][0]["theta_end"][3] == pytest.approx(0.4 + 0.5 * 0.3)   # θ4 + m_p d
    assert "payload 0.5 kg" in text


@pytest.mark.parametrize("argv, word", [
    (["--laws", "gradient"], "no sampled form"),
    (["--t-end", "-1"], "--t-end"),
    (["--integrator", "rk45"], "invalid choice"),
    (["--payload-mass", "-1"], "payload mass"),
    (["--encoder-counts", "0"], "encoder_counts"),
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
