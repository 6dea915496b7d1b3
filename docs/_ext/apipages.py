"""Write the API reference's pages: one per public module of ivdrem, from its ``__all__``.

A module is public when no part of its dotted name starts with ``_``.  Each name of its
``__all__`` is documented once, in its home module (the module that defines it, when that
module is public); a package that re-exports a name lists it with a link to that entry.
A name defined in a private module (``ivdrem.blocks._core``) is documented in the public
module that exports it.  Modules without ``__all__`` document their public members.

The pages are written to ``docs/api/generated/`` when the build starts (git-ignored);
tests/test_site.py checks the built site's inventory against every ``__all__``.
"""
from __future__ import annotations

import functools
import importlib
import pkgutil
import re
from pathlib import Path

OUT = Path(__file__).resolve().parents[1] / "api" / "generated"


@functools.lru_cache(maxsize=None)
def public_modules(package: str = "ivdrem") -> list[str]:
    """Dotted names of ivdrem's public modules (no part starting with ``_``), sorted."""
    root = importlib.import_module(package)
    names = [package]
    for info in pkgutil.walk_packages(root.__path__, package + "."):
        if not any(part.startswith("_") for part in info.name.split(".")):
            names.append(info.name)
    return tuple(sorted(names))


def _defines(module, name: str) -> bool:
    """Whether `module`'s own source assigns `name` at top level (for data without __module__)."""
    try:
        src = Path(module.__file__).read_text(encoding="utf-8")
    except (OSError, TypeError):
        return False
    return re.search(rf"^{re.escape(name)}\s*(:[^=\n]*)?=", src, re.M) is not None


def home_module(module_name: str, name: str) -> str:
    """Where `module_name.name` is documented: the defining module if public, else here."""
    module = importlib.import_module(module_name)
    obj = getattr(module, name)
    home = getattr(obj, "__module__", None)
    if not isinstance(home, str) or not hasattr(obj, "__qualname__"):
        # data: documented in the public module whose source assigns it (its #: comment)
        if _defines(module, name):
            return module_name
        for other in public_modules():
            omod = importlib.import_module(other)
            if (name in getattr(omod, "__all__", ()) and _defines(omod, name)
                    and getattr(omod, name, None) is obj):
                return other
        return module_name
    if (home != module_name and home.startswith("ivdrem")
            and not any(p.startswith("_") for p in home.split("."))):
        try:
            hmod = importlib.import_module(home)
        except ImportError:
            return module_name
        listed = getattr(hmod, "__all__", None)
        if (listed is None or name in listed) and getattr(hmod, name, None) is obj:
            return home
    return module_name


def _comment_doc(module_name: str, name: str) -> str:
    """The ``#:`` comment block that documents `name` where no assignment carries it: a
    name served by the module's ``__getattr__`` (the block names it as ````NAME````) or
    imported under its public name (the block stands just above ``... as NAME``)."""
    module = importlib.import_module(module_name)
    try:
        lines = Path(module.__file__).read_text(encoding="utf-8").splitlines()
    except (OSError, TypeError):
        return ""
    i = 0
    while i < len(lines):
        if not lines[i].startswith("#:"):
            i += 1
            continue
        j = i
        while j < len(lines) and lines[j].startswith("#:"):
            j += 1
        block = [line[2:].strip() for line in lines[i:j]]
        after = lines[j] if j < len(lines) else ""
        if f"``{name}``" in " ".join(block) or re.search(rf"\bas {re.escape(name)}\b", after):
            return "\n".join(block)
        i = j
    return ""


def data_doc(module_name: str, name: str) -> str:
    """The documentation of a module-level name that is not a function or class: its ``#:``
    comment (or the string after its assignment), else :func:`_comment_doc`."""
    from sphinx.pycode import ModuleAnalyzer
    docs = ModuleAnalyzer.for_module(module_name).find_attr_docs().get(("", name))
    return "\n".join(docs).strip() if docs else _comment_doc(module_name, name)


def module_page(module_name: str) -> str:
    module = importlib.import_module(module_name)
    listed = getattr(module, "__all__", None)
    lines = [f"# {module_name}", "", "```{eval-rst}", f".. automodule:: {module_name}"]
    if listed is None:
        lines += ["   :members:", "```", ""]
        return "\n".join(lines)
    here = [n for n in listed if home_module(module_name, n) == module_name]
    elsewhere = [n for n in listed if n not in here]
    # names autodoc cannot document from their assignment: served by __getattr__ or
    # imported; their #: comment becomes the entry's text
    from sphinx.pycode import ModuleAnalyzer
    attr_docs = ModuleAnalyzer.for_module(module_name).find_attr_docs()
    by_comment = [n for n in here if not hasattr(getattr(module, n), "__qualname__")
                  and ("", n) not in attr_docs and _comment_doc(module_name, n)]
    members = [n for n in here if n not in by_comment]
    if members:
        lines += [f"   :members: {', '.join(members)}"]   # listed names, imported or not
    else:
        lines += ["   :no-members:"]
    for n in by_comment:
        lines += ["", f".. autodata:: {module_name}.{n}", "   :no-value:", ""]
        lines += ["   " + line for line in _comment_doc(module_name, n).splitlines()]
    lines += ["```", ""]
    if elsewhere:
        lines += ["Also exported here (documented in their own modules):", ""]
        for n in elsewhere:
            home = home_module(module_name, n)
            lines.append(f"- {{py:obj}}`{module_name}.{n} <{home}.{n}>`")
        lines.append("")
    return "\n".join(lines)


def write_pages(app=None) -> list[str]:
    OUT.mkdir(parents=True, exist_ok=True)
    written = []
    for name in public_modules():
        text = module_page(name)
        path = OUT / f"{name}.md"
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")   # unchanged pages keep their time stamp
        written.append(path.name)
    for stale in OUT.glob("*.md"):
        if stale.name not in written:
            stale.unlink()
    return written


def setup(app):
    app.connect("builder-inited", write_pages)
    app.connect("autodoc-process-docstring", _process_docstring)
    return {"parallel_read_safe": True, "parallel_write_safe": True}


# ------------------------------------------------------------------ plain-text bars
_LITERAL = re.compile(r"(``.+?``|`[^`]+`)")


def escape_bars(line: str) -> str:
    """``|x|`` and ``||x||`` are norms in ivdrem's docstrings, never reStructuredText
    substitutions or line blocks: escape each ``|`` outside literals, leaving the lines
    of grid tables (``+---+`` borders, rows that start and end with ``|``) alone."""
    stripped = line.strip()
    if stripped.startswith(("+-", "+=")) or (len(stripped) > 2 and stripped[0] == "|"
                                             and stripped[-1] == "|" and " | " in stripped):
        return line
    parts = _LITERAL.split(line)
    for i in range(0, len(parts), 2):           # the even parts are outside literals
        parts[i] = parts[i].replace("|", r"\|")
    return "".join(parts)


_BORDER = re.compile(r"^\s*=+(\s+=+)+\s*$")


def escape_docstring(lines: list[str]) -> list[str]:
    """:func:`escape_bars` on every line; inside a simple table (``====  ====`` borders),
    where a backslash would shift the columns, a bar becomes ``∣`` (U+2223) instead."""
    out, in_table = [], False
    for i, line in enumerate(lines):
        if _BORDER.match(line):
            nxt = lines[i + 1] if i + 1 < len(lines) else ""
            if in_table and not nxt.strip():
                in_table = False                 # the bottom border
            else:
                in_table = True
            out.append(line)
        elif in_table:
            out.append(line.replace("|", "\u2223"))
        else:
            out.append(escape_bars(line))
    return out


def _process_docstring(app, what, name, obj, options, lines):
    lines[:] = escape_docstring(lines)
