"""Named views of a block's flat vectors: what a named-port kernel receives.

A kernel declared with ``named_ports=True`` (every library block) is called as
``update(t, x, u, dx, *params)`` / ``output(t, x, u, y, *params)`` where ``x``, ``u``,
``dx`` and ``y`` are namedtuples of 1-D float64 views, one field per declared port or
state: ``u.q``, ``u.theta_hat``, ``x.Phi_f``, ``dx.Phi_f``, ``y.Pi``.  Writing into a view
of ``dx`` or ``y`` writes the engine's flat vector; nothing is copied.  A size-1 port is a
1-element view (``u.mu[0]``, ``y.Delta[0] = ...``), so inputs and outputs read alike.
Matrix-valued signals stay flat row-major (``u.Pi.reshape((n, ntheta))``).

Two forms, one kernel.  The reference path (python-control calling :func:`make_block`'s
wrappers) passes namedtuples of views (:func:`views`).  The compiled path compiles the
kernel's *flat form* (:func:`flat_form`): the same source with ``u.q[i]`` replaced by
``u[a + i]``, ``u.q.shape`` by ``(size,)`` and any other use of ``u.q`` by a local view
``u[a:b]`` made once at the top, the offsets taken from the declaration, so the generated
code is what a hand-written flat kernel would be (numba passes namedtuple
arguments to a separately compiled function at a cost comparable to the kernels' own
work: measured 1.8x the paper loop's right-hand side).  Using a port that is not declared,
or ``u`` as a whole, is an error naming the kernel and the port.

The namedtuple classes live in this module under names that spell their fields
(:func:`port_class`), and a missing name is rebuilt on demand (module ``__getattr__``), so
they pickle by reference (numba's cache, multiprocessing) and load in a fresh process.
"""
from __future__ import annotations

import keyword
from collections import namedtuple

__all__ = ["port_class", "class_name", "views", "check_port_names", "flat_form", "PortError"]

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


# ------------------------------------------------------------------ the compiled form
# numba passes a namedtuple of views to a separately compiled kernel at a measurable cost
# (about 1.8x the right-hand side of the paper loop), and each view is an NRT incref/decref,
# so the compiled path gets the kernel rewritten to the flat convention with the offsets
# from the declaration (what the library's kernels did by hand before).  The reference
# path runs the kernel as written on namedtuples (flat_kernel in _core); tests compare them.
import ast
import hashlib
import inspect
import linecache
import textwrap

_flat_cache = {}


class PortError(ValueError):
    """A named-port kernel that uses its ports in a way the engine cannot provide."""


def flat_form(fn, role, layout, *, runtime_offsets=False):
    """`fn` (a named-port kernel) as a function of flat vectors ``(t, x, u, out, *params)``.

    `layout` is ``[(fields, ports)]`` for x, u and out (ports: [(name, size)]).  The
    result has real source (registered in linecache) so the compiled path can read and
    compile it like any kernel; one function per (kernel, layout), named
    ``<kernel>__ports_<hash>``.

    With ``runtime_offsets`` the ports' bounds are arguments instead of literals: the
    function is ``(t, x, u, out, *bounds, *params)``, `bounds` the cumulative port offsets
    of x, u and out (``len(fields) + 1`` integers each, from 0 to the vector's size), and
    every used port is a view ``u[lo:hi]`` made once at the top; its source depends on the
    kernel, the role and the field names only, so one compiled function serves every size
    (:func:`_bound_names`).  Constant indices are still checked against `layout`'s sizes
    here.
    """
    key = (fn, role, tuple((tuple(f), tuple(p)) for f, p in layout), runtime_offsets)
    if key in _flat_cache:
        return _flat_cache[key]
    src = textwrap.dedent(inspect.getsource(fn))
    tree = ast.parse(src)
    fdef = tree.body[0]
    if not isinstance(fdef, ast.FunctionDef) or len(fdef.args.args) < 4:
        raise PortError(f"kernel {fn.__name__}: expected def {fn.__name__}(t, x, u, out, ...)")
    args = [a.arg for a in fdef.args.args]
    taken = {n.id for n in ast.walk(fdef) if isinstance(n, ast.Name)}
    bounds = (_bound_names(args[1:4], [f for f, _ in layout], taken | set(args))
              if runtime_offsets else None)
    where = {}                      # argument name -> {field: (start, stop, size, rank)}
    for k, (arg, (fields, ports)) in enumerate(zip(args[1:4], layout)):
        offs, i = {}, 0
        for j, (f, (_, size)) in enumerate(zip(fields, ports)):
            if runtime_offsets:     # the bounds' names (ast.Name), the size for the checks
                offs[f] = (bounds[k][j], bounds[k][j + 1], size, j)
            else:
                offs[f] = (i, i + size, size, i)
            i += size
        where[arg] = offs
    used = {}                       # local name -> (argument, start, stop), in first-use order

    def port_of(node):
        """(argument, start, stop, size) if `node` is ``<x|u|out>.<declared port>``."""
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in where and node.attr in where[node.value.id]):
            return (node.value.id, *where[node.value.id][node.attr][:3])
        return None

    def plus(a, idx):               # a + idx for a literal offset a, without "0 +"
        if isinstance(idx, ast.Constant):
            return ast.Constant(a + idx.value)
        if a == 0:
            return idx
        return ast.BinOp(ast.Constant(a), ast.Add(), idx)

    class Rewrite(ast.NodeTransformer):
        # literal offsets: u.q[i] -> u[a + i] and u.q.shape -> (size,), no view at all (a
        # view costs an NRT incref/decref in numba); any other use of u.q -> a view made
        # once at the top.  Runtime offsets: every u.q -> that view (u[lo + i] would keep
        # numba's negative-index wrap-around, which LLVM cannot drop for an offset it does
        # not know is >= 0: the Panda's averaging 4-8x slower; a view's index i from a
        # range is known >= 0)
        def visit_Subscript(self, node):
            port = port_of(node.value)
            if port is not None and not isinstance(node.slice, (ast.Slice, ast.Tuple)):
                arg, a, b, size = port
                idx = self.visit(node.slice)
                if isinstance(idx, ast.Constant) and isinstance(idx.value, int):
                    k = idx.value + (size if idx.value < 0 else 0)
                    if not 0 <= k < size:
                        raise PortError(f"kernel {fn.__name__}: index {idx.value} out of "
                                        f"range for {arg}.{node.value.attr} (size {size})")
                    flat_idx = plus(a, ast.Constant(k)) if isinstance(a, int) else None
                else:           # a port index must be >= 0 (documented)
                    flat_idx = plus(a, idx) if isinstance(a, int) else None
                if flat_idx is None:        # runtime offsets: the port's view
                    node.slice = idx
                    node.value = self.visit(node.value)
                    return node
                return ast.copy_location(ast.Subscript(ast.Name(arg, ast.Load()), flat_idx,
                                                       node.ctx), node)
            return self.generic_visit(node)

        def visit_Attribute(self, node):
            port = port_of(node.value)
            if port is not None and node.attr == "shape" and isinstance(port[1], int):
                return ast.copy_location(ast.Tuple([ast.Constant(port[3])], ast.Load()), node)
            if isinstance(node.value, ast.Name) and node.value.id in where:
                arg, field = node.value.id, node.attr
                if field not in where[arg]:
                    raise PortError(
                        f"kernel {fn.__name__}: {arg}.{field} is not a declared "
                        f"{_what(role, args.index(arg))} (they are: "
                        f"{', '.join(where[arg]) or 'none'})")
                local = f"{arg}_{field}_view"
                while local in taken and local not in used:
                    local += "_"
                a, b, _, rank = where[arg][field]
                used.setdefault(local, (arg, a, b, rank))
                return ast.copy_location(ast.Name(id=local, ctx=ast.Load()), node)
            return self.generic_visit(node)

        def visit_Name(self, node):
            if node.id in where:
                raise PortError(
                    f"kernel {fn.__name__}: uses '{node.id}' as a whole; a named-port kernel "
                    f"reads its ports as {node.id}.<port> (or declare named_ports=False)")
            return node

    body = [Rewrite().visit(stmt) for stmt in fdef.body]
    fields_key = tuple(tuple(f) for f, _ in layout)
    if runtime_offsets and (fn, role, fields_key) in _flat_cache:
        # the same source for every size: one function object, compiled once
        flat = _flat_cache[key] = _flat_cache[(fn, role, fields_key)]
        return flat
    order = sorted(used.items(), key=lambda kv: (args.index(kv[1][0]), kv[1][3]))
    head = [ast.parse(f"{local} = {arg}[{a}:{b}]").body[0] for local, (arg, a, b, _) in order]
    if runtime_offsets:
        fdef.args.args[4:4] = [ast.arg(n) for names in bounds for n in names]
        digest_of = repr((role, fields_key, "runtime offsets as views"))
    else:
        digest_of = repr(key[1:3])
    digest = hashlib.sha256(digest_of.encode() + src.encode()).hexdigest()[:12]
    fdef.name = f"{fn.__name__}__ports_{digest}"
    fdef.body = head + body
    fdef.decorator_list = []
    new_src = (f"# {fn.__module__}.{fn.__name__} with its named ports as views of the flat "
               f"vectors (generated by ivdrem.blocks._ports)\n" + ast.unparse(ast.fix_missing_locations(tree)) + "\n")
    filename = f"<ivdrem-ports {fn.__module__}.{fdef.name}>"
    lines = new_src.splitlines(keepends=True)
    linecache.cache[filename] = (len(new_src), None, lines, filename)
    ns = {}
    exec(compile(new_src, filename, "exec"), fn.__globals__.copy(), ns)
    flat = ns[fdef.name]
    # the kernel's own module globals (np, model, helpers), as the compiled path checks them
    flat = type(fn)(flat.__code__, fn.__globals__, fdef.name)
    flat.__module__ = fn.__module__
    flat.__qualname__ = fdef.name
    flat.named_kernel = fn          # not __wrapped__: inspect would show fn's source
    _flat_cache[key] = flat
    if runtime_offsets:
        _flat_cache[(fn, role, fields_key)] = flat
    return flat


def _bound_names(args, fields, taken):
    """[[name of bound j of argument k]]: ``len(fields[k]) + 1`` names per argument of
    x, u, out, none of them a name the kernel uses."""
    out = []
    for arg, fs in zip(args, fields):
        names = []
        for j in range(len(fs) + 1):
            name = f"{arg}_at_{j}"
            while name in taken:
                name += "_"
            names.append(name)
        out.append(names)
    return out


def _what(role, position):
    if position == 1:
        return "state"
    if position == 2:
        return "input port"
    return "output port" if role == "output" else "state"
