"""One build step pyproject.toml cannot state: the repository's examples/ directory (the
configurations, studies and custom_law.py the README runs) is copied into the built package
as ``ivdrem/_examples``, so that a wheel carries them and ``ivdrem examples DIR`` writes
them out.  examples/ stays the one source; an editable install reads it in place
(``ivdrem._bundled``).  Everything else is in pyproject.toml."""
import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

EXAMPLES = Path(__file__).resolve().parent / "examples"


class build_py_with_examples(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return             # the source tree's examples/ is read in place
        target = Path(self.build_lib) / "ivdrem" / "_examples"
        target.mkdir(parents=True, exist_ok=True)
        for f in sorted(EXAMPLES.iterdir()):
            if f.is_file() and f.suffix in (".toml", ".py"):
                shutil.copy2(f, target / f.name)


setup(cmdclass={"build_py": build_py_with_examples})
