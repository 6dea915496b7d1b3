"""Write the front page's figure, docs/_static/theta-error.png: the report's Figure 3.

The paper's experiment with its embedded default configuration (both laws, 300 s), the
report's own figure builder (ivdrem.reports.figures.fig_theta_error), saved as a small PNG.
Run from the clone:  ./run python docs/front_figure.py   (about a minute with warm caches)
"""
from pathlib import Path

import matplotlib
from matplotlib import rc_context

from ivdrem.experiments.paper import run_paper
from ivdrem.reports.figures import RC, fig_theta_error

OUT = Path(__file__).resolve().parent / "_static" / "theta-error.png"

if __name__ == "__main__":
    matplotlib.use("Agg")
    with rc_context(RC):
        run = run_paper(progress=False)                 # examples/paper.toml's values
        spec = fig_theta_error(run)
        spec.figure.savefig(OUT, dpi=72)
    print(f"{OUT}: {spec.title}; {OUT.stat().st_size} bytes")
