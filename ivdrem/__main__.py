"""``python -m ivdrem``: the command line (:mod:`ivdrem.cli`)."""
from .cli import run

run()
