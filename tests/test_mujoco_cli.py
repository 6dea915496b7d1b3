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
