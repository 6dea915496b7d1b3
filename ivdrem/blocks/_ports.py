"""Named views of a block's flat vectors: what a named-port kernel receives.

A kernel declared with ``named_ports=True`` (every library block) is called as
``update(t, x, u, dx, *params)`` / ``output(t, x, u, y, *params)`` where ``x``, ``u``,
``dx`` and ``y`` are namedtuples of 1-D float64 views, one field per declared port or
state: ``u.q``, ``u.theta_hat``, ``x.Phi_f``, ``dx.Phi_f``, ``y.Pi``.  Writing into a view
of ``dx`` or ``y`` writes the engine's flat vector; nothing is copied.  A size-1 port is a
1-element view (``u.mu[0]``, ``y.Delta[0] = ...``), so inputs and outputs read alike.
Matrix-valued signals stay flat row-major (``u.Pi.reshape((n, ntheta))``).

The namedtuple classes live in this module under names that spell their fields
(:func:`port_class`), and a missing name is rebuilt on demand (module ``__getattr__``):
numba's on-disk cache pickles the classes of a kernel's argument types by module and name,
so a fresh process, or another diagram using the same kernel with the same ports, finds
the same class and reuses the compiled kernel.
"""
from __future__ import annotations

import keyword
from collections import namedtuple

__all__ = ["port_class", "class_name", "views", "check_port_names"]

_PREFIX = "Ports_"
_classes = {}


def class_name(fields) -> str:
    """Identifier naming the namedtuple class of `fields`: each '_' of a field becomes
    '_u', fields are joined by '_s' (decodable, so the name alone rebuilds the class)."""
    return _PREFIX + "_s".join(f.replace("_", "_u") for f in fields)


def _fields_of(name: str) -> tuple:
    body = name[len(_PREFIX):]
    if not body:
        return ()
    fields, cur, i = [], [], 0
    while i < len(body):
        c = body[i]
        if c == "_":
            nxt = body[i + 1] if i + 1 < len(body) else ""
            if nxt == "u":
                cur.append("_")
            elif nxt == "s":
                fields.append("".join(cur))
                cur = []
            else:
                raise AttributeError(name)
            i += 2
        else:
            cur.append(c)
            i += 1
    fields.append("".join(cur))
    return tuple(fields)


def port_class(fields):
    """The namedtuple class with these fields (one class per field tuple, per process)."""
    fields = tuple(fields)
    cls = _classes.get(fields)
    if cls is None:
        name = class_name(fields)
        cls = namedtuple(name, fields)
        cls.__module__ = __name__
        cls.__qualname__ = name
        _classes[fields] = cls
        globals()[name] = cls
    return cls


def __getattr__(name):                  # PEP 562: rebuild a class from its name
    if name.startswith(_PREFIX):
        fields = _fields_of(name)
        if all(f.isidentifier() for f in fields):
            return port_class(fields)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def check_port_names(block, kind, ports):
    """Port names must be usable as namedtuple fields: identifiers, no keyword, no
    leading underscore, no duplicate; the message names the block and the port."""
    seen = set()
    for name, _ in ports:
        if (not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name)
                or name.startswith("_")):
            raise ValueError(f"block '{block}': {kind} port name {name!r} cannot be a named "
                             "port (use a Python identifier not starting with '_'), or "
                             "declare the block with named_ports=False")
        if name in seen:
            raise ValueError(f"block '{block}': two {kind} ports are named {name!r}")
        seen.add(name)


def views(cls, ports, vec):
    """cls of views of the flat vector `vec`, one per (name, size) in `ports`."""
    out, i = [], 0
    for _, size in ports:
        out.append(vec[i:i + size])
        i += size
    return cls(*out)
