"""The examples a user gets with the package: the repository's ``examples/`` directory
(configurations, studies, ``custom_law.py``), carried in a wheel as ``ivdrem/_examples``
(copied there at build time by setup.py) and read in place from a source tree or an
editable install.  ``ivdrem examples DIR`` writes them out."""
from __future__ import annotations

from pathlib import Path

__all__ = ["examples_dir", "example_files", "write_examples", "ExamplesError"]

_PACKAGE = Path(__file__).resolve().parent


class ExamplesError(OSError):
    """The examples cannot be found or written; the message says why."""


def examples_dir() -> Path:
    """The directory holding the examples: the wheel's ``ivdrem/_examples``, else the
    source tree's ``examples/`` beside the package."""
    for d in (_PACKAGE / "_examples", _PACKAGE.parent / "examples"):
        if d.is_dir() and any(d.glob("*.toml")):
            return d
    raise ExamplesError("this installation of ivdrem carries no examples (neither "
                        f"{_PACKAGE / '_examples'} nor {_PACKAGE.parent / 'examples'} exists); "
                        "reinstall it from a wheel or a source tree")


def example_files() -> list[Path]:
    """The example files, sorted by name."""
    return sorted(p for p in examples_dir().iterdir()
                  if p.is_file() and p.suffix in (".toml", ".py"))


def _summary(path: Path) -> str:
    """The first comment line of an example (what it is)."""
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line.startswith("#"):
            return line.lstrip("# ").strip()
        if line.startswith('"""'):
            return line.strip('"').strip()
    return ""


def describe_examples() -> str:
    """One line per example: its name and what it is."""
    files = example_files()
    width = max(len(p.name) for p in files)
    return "\n".join(f"{p.name:<{width}}  {_summary(p)}" for p in files)


def write_examples(dest, *, overwrite: bool = False) -> list[Path]:
    """Write every example into the directory `dest` (made if missing); returns the files
    written.  A file already there with the same text is left alone; one with other text
    is the user's: nothing is written unless `overwrite` (checked for every file before
    the first is written).  Each file is written atomically."""
    from ._atomic import write_text_atomic
    from ._paths import OutputLocationError, check_writable_dir
    dest = Path(dest)
    try:
        check_writable_dir(dest, "examples directory")
    except OutputLocationError as exc:
        raise ExamplesError(str(exc)) from None
    todo, differing = [], []
    for src in example_files():
        text = src.read_text(encoding="utf-8")
        target = dest / src.name
        if target.is_file() and target.read_bytes() == text.encode("utf-8"):
            continue
        if target.exists() or target.is_symlink():
            if not target.is_file():
                raise ExamplesError(f"{target} exists and is not a regular file; move it "
                                    "or choose another directory")
            differing.append(target)
        todo.append((target, text))
    if differing and not overwrite:
        raise ExamplesError(
            "refusing to overwrite " + ", ".join(str(p) for p in differing)
            + ": they exist with other text (your edits?); move them, choose another "
            "directory, or pass --overwrite")
    return [write_text_atomic(target, text) for target, text in todo]
