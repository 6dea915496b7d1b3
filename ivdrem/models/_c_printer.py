"""C99 from the rigid-body kernels' Python (:mod:`ivdrem.models.rigid_body`): the one source
of the recursive Newton-Euler algorithm and the Cholesky, printed for a URDF model's C face.

The printer knows the small subset the kernels are written in, and refuses anything else
(:class:`CPrintError` naming the function and line):

* a kernel's parameters are annotated with strings: ``"int"``, ``"real"``, ``"float"``,
  ``"cplx"``, ``"bool"`` for scalars, ``"real[N,6]"`` / ``"const float[N,3,3]"`` /
  ``"int[N]"`` for arrays whose shape is fixed at generation (``N``, ``NS`` ... are the
  macros of the C face) or given by an ``"int"`` parameter of the kernel
  (``"real[N,NTHETA,ncol]"``); its return annotation is ``"int"``, ``"real"``, ``"float"`` or
  absent (void).  ``real`` is the type the kernel computes in (``double``, or ``double
  complex`` when printed for the complex step: ``print_kernels(..., real="double complex")``),
  ``float`` always ``double`` (the chain's constants, a modulus), ``cplx`` always
  ``double complex``;
* statements: assignments to a name or an indexed array element (``+=`` and friends),
  ``for`` over ``range`` (a constant step), ``while``, ``if``/``elif``/``else``, ``break``,
  ``return``, calls of other kernels, ``x = y.shape[d]`` (a size: the macro),
  ``x = np.empty(shape)`` / ``np.zeros(shape)`` (an array on the stack, sizes from
  macros and literals), ``dt = y.dtype`` (ignored: C is real only);
* expressions: numbers, names, ``a[i, j]`` (flattened row major), ``a[i]`` of a 2- or
  3-dimensional array as an argument (a pointer to that row), arithmetic, comparisons,
  ``and``/``or``/``not``, ``x if c else y``, ``np.cos``, ``np.sin``, ``np.sqrt``,
  ``np.tanh``, ``abs``, ``np.inf``, ``1j``, ``z.imag``; ``np.empty(shape, dtype=a.dtype)``
  an array of ``a``'s element type (``float`` without ``dtype``).

Locals are declared at the top of the function, of the widest type assigned to them
(int < float < real < cplx).  Module-level names the kernels read (``PIVOT_RTOL``) are printed
as their values.
"""
from __future__ import annotations

import ast
import inspect
import textwrap

__all__ = ["CPrintError", "print_kernels"]


class CPrintError(ValueError):
    """A kernel uses Python the printer does not translate."""


_MATH = {"cos": "cos", "sin": "sin", "sqrt": "sqrt", "tanh": "tanh", "abs": "fabs"}
#: the same functions of a complex argument (<complex.h>)
_CMATH = {"cos": "ccos", "sin": "csin", "sqrt": "csqrt", "tanh": "ctanh", "abs": "cabs"}
#: the kinds of a value, narrowest first (the C type of each: _Printer.ctype)
_KINDS = ("int", "float", "real", "cplx")


def _join(*kinds):
    return _KINDS[max(_KINDS.index(k) for k in kinds)]
_OPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Mod: "%"}
_CMP = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==",
        ast.NotEq: "!="}


def c_double(x):
    """A Python float as a C99 double literal (INFINITY for an infinite one)."""
    s = repr(float(x))
    if s == "inf":
        return "INFINITY"
    if s == "-inf":
        return "(-INFINITY)"
    return s if ("e" in s or "." in s) else s + ".0"


def _parse_type(text):
    """('int'|'real'|'bool', shape tuple or None, const)"""
    t = text.strip()
    const = t.startswith("const ")
    if const:
        t = t[6:].strip()
    if "[" in t:
        base, dims = t[:-1].split("[", 1)
        return base.strip(), tuple(d.strip() for d in dims.split(",")), const
    return t, None, const


class _Function:
    def __init__(self, fn, printer):
        self.fn = fn
        self.name = fn.__name__
        self.printer = printer
        src = textwrap.dedent(inspect.getsource(fn))
        self.tree = ast.parse(src).body[0]
        self.arrays = {}        # name -> shape (tuple of C expressions)
        self.elems = {}         # array name -> kind of its elements
        self.dtypes = {}        # local name of ``a.dtype`` -> the array a
        self.scalars = {}       # name -> kind ("int" | "float" | "real" | "cplx")
        self.params = []
        self.sizes = {}         # local size alias -> C expression
        self.ret = None
        ann = self.ann = {}
        # an array dimension may be an int parameter of the kernel (a column count that
        # differs between callers); the others are the C face's macros
        int_params = {a.arg for a in self.tree.args.args
                      if isinstance(a.annotation, ast.Constant) and a.annotation.value == "int"}
        for a in self.tree.args.args:
            if not (isinstance(a.annotation, ast.Constant) and isinstance(a.annotation.value, str)):
                self.fail(self.tree, f"parameter {a.arg!r} has no type annotation (a string)")
            ann[a.arg] = a.annotation.value
            base, shape, const = _parse_type(ann[a.arg])
            shape = None if shape is None else tuple(d if d in int_params else printer.dim(d)
                                                     for d in shape)
            kind = "int" if base == "bool" else base
            if kind not in _KINDS:
                self.fail(self.tree, f"parameter {a.arg!r} has unknown type {base!r}")
            ctype = printer.ctype(kind)
            if shape is None:
                self.scalars[a.arg] = kind
                self.params.append(f"{ctype} {a.arg}")
            else:
                self.arrays[a.arg] = shape
                self.elems[a.arg] = kind
                self.params.append(f"{'const ' if const else ''}{ctype} *{a.arg}")
        r = self.tree.returns
        if r is not None:
            self.ret = printer.ctype(r.value)
        self._collect_locals()

    def fail(self, node, msg):
        line = getattr(node, "lineno", 0) + self.fn.__code__.co_firstlineno - 1
        raise CPrintError(f"{self.name} (line {line}): {msg}")

    # ---------------------------------------------------------------- locals and types
    def _collect_locals(self):
        assigned = {}
        allocs = []
        for node in ast.walk(self.tree):
            if isinstance(node, ast.Assign):
                if len(node.targets) != 1:
                    self.fail(node, "chained assignment")
                t = node.targets[0]
                if isinstance(t, ast.Name):
                    v = node.value
                    if self._is_alloc(v):
                        self.arrays[t.id] = self._alloc_shape(v)
                        allocs.append((t.id, v))
                    elif (isinstance(v, ast.Attribute) and v.attr == "dtype"):
                        self.dtypes[t.id] = v.value.id
                        continue
                    elif (isinstance(v, ast.Subscript) and isinstance(v.value, ast.Attribute)
                          and v.value.attr == "shape"):
                        arr = v.value.value.id
                        self.sizes[t.id] = self.arrays[arr][v.slice.value]
                        self.scalars[t.id] = "int"
                    else:
                        assigned.setdefault(t.id, []).append(v)
                elif not isinstance(t, ast.Subscript):
                    self.fail(node, "assignment to a tuple (write one per line)")
            elif isinstance(node, ast.For):
                if not isinstance(node.target, ast.Name):
                    self.fail(node, "for over a tuple")
                self.scalars[node.target.id] = "int"
            elif isinstance(node, ast.AugAssign) and isinstance(node.target, ast.Name):
                assigned.setdefault(node.target.id, []).append(node.value)
        for name, v in allocs:          # element type: dtype=a.dtype (or an alias), else float
            kw = {k.arg: k.value for k in v.keywords}
            dt = kw.get("dtype")
            src = None
            if isinstance(dt, ast.Attribute) and dt.attr == "dtype":
                src = dt.value.id
            elif isinstance(dt, ast.Name):
                src = self.dtypes.get(dt.id)
            elif dt is not None:
                self.fail(v, f"dtype {ast.unparse(dt)} (write dtype=a.dtype)")
            self.elems[name] = self.elems.get(src, "float") if src else "float"
        for name in assigned:
            if name not in self.scalars:
                self.scalars[name] = "int"
        for _ in range(4):              # settle: a name is as wide as the widest of its values
            for name, values in assigned.items():
                if name in self.params_names():
                    continue
                self.scalars[name] = _join(self.scalars[name],
                                           *(self.type_of(v) for v in values))
        self.locals = [n for n in self.scalars if n not in self.params_names()]

    def params_names(self):
        return {a.arg for a in self.tree.args.args}

    @staticmethod
    def _is_alloc(v):
        return (isinstance(v, ast.Call) and isinstance(v.func, ast.Attribute)
                and isinstance(v.func.value, ast.Name) and v.func.value.id == "np"
                and v.func.attr in ("empty", "zeros"))

    def _alloc_shape(self, v):
        arg = v.args[0]
        elts = arg.elts if isinstance(arg, ast.Tuple) else [arg]
        return tuple(self.size_expr(e) for e in elts)

    def size_expr(self, e):
        if isinstance(e, ast.Constant) and isinstance(e.value, int):
            return str(e.value)
        if isinstance(e, ast.Name) and e.id in self.sizes:
            return self.sizes[e.id]
        if isinstance(e, ast.BinOp) and type(e.op) in (ast.Mult, ast.Add):
            return f"({self.size_expr(e.left)} {_OPS[type(e.op)]} {self.size_expr(e.right)})"
        self.fail(e, f"an array size must be a literal or a size: {ast.unparse(e)}")

    def type_of(self, e):
        """The kind of an expression: "int", "float", "real" or "cplx"."""
        if isinstance(e, ast.Constant):
            if isinstance(e.value, (bool, int)):
                return "int"
            return "cplx" if isinstance(e.value, complex) else "float"
        if isinstance(e, ast.Name):
            if e.id in self.sizes:
                return "int"
            if e.id in self.scalars:
                return self.scalars[e.id]
            g = self.fn.__globals__.get(e.id)
            return "int" if isinstance(g, int) and not isinstance(g, bool) else "float"
        if isinstance(e, ast.Subscript):
            if isinstance(e.value, ast.Attribute) and e.value.attr == "shape":
                return "int"
            base = e.value.id if isinstance(e.value, ast.Name) else None
            return self.elems.get(base, "real")
        if isinstance(e, ast.Attribute):
            return "float"                      # np.inf, z.imag
        if isinstance(e, ast.BinOp):
            k = _join(self.type_of(e.left), self.type_of(e.right))
            return _join(k, "float") if isinstance(e.op, ast.Div) else k
        if isinstance(e, ast.UnaryOp):
            return "int" if isinstance(e.op, ast.Not) else self.type_of(e.operand)
        if isinstance(e, (ast.Compare, ast.BoolOp)):
            return "int"
        if isinstance(e, ast.IfExp):
            return _join(self.type_of(e.body), self.type_of(e.orelse))
        if isinstance(e, ast.Call):
            f = e.func
            if isinstance(f, ast.Name) and f.id == "abs":
                return "float"
            if isinstance(f, ast.Attribute) and f.attr in _MATH:
                return _join("float", *(self.type_of(a) for a in e.args))
            if isinstance(f, ast.Name) and f.id in self.printer.returns:
                return self.printer.returns[f.id] or "int"
        return "real"

    # ---------------------------------------------------------------- expressions
    def expr(self, e):
        if isinstance(e, ast.Constant):
            if isinstance(e.value, bool):
                return "1" if e.value else "0"
            if isinstance(e.value, int):
                return str(e.value)
            if isinstance(e.value, float):
                return c_double(e.value)
            if isinstance(e.value, complex) and e.value.real == 0.0:
                return f"({c_double(e.value.imag)} * I)"
            self.fail(e, f"constant {e.value!r}")
        if isinstance(e, ast.Name):
            if e.id in self.sizes:
                return self.sizes[e.id]
            if e.id in self.scalars or e.id in self.arrays:
                return e.id
            g = self.fn.__globals__.get(e.id)
            if isinstance(g, (int, float)) and not isinstance(g, bool):
                return c_double(g) if isinstance(g, float) else str(g)
            self.fail(e, f"unknown name {e.id!r}")
        if isinstance(e, ast.Attribute):
            if isinstance(e.value, ast.Name) and e.value.id == "np" and e.attr == "inf":
                return "INFINITY"
            if e.attr == "imag":
                return f"cimag({self.expr(e.value)})"
            self.fail(e, f"attribute {ast.unparse(e)}")
        if isinstance(e, ast.Subscript):
            if isinstance(e.value, ast.Attribute) and e.value.attr == "shape":
                return self.arrays[e.value.value.id][e.slice.value]
            return self.subscript(e)
        if isinstance(e, ast.BinOp):
            if type(e.op) not in _OPS:
                self.fail(e, f"operator {type(e.op).__name__}")
            return f"({self.expr(e.left)} {_OPS[type(e.op)]} {self.expr(e.right)})"
        if isinstance(e, ast.UnaryOp):
            if isinstance(e.op, ast.USub):
                return f"(-{self.expr(e.operand)})"
            if isinstance(e.op, ast.Not):
                return f"(!{self.expr(e.operand)})"
            self.fail(e, "unary operator")
        if isinstance(e, ast.Compare):
            parts = []
            left = e.left
            for op, right in zip(e.ops, e.comparators):
                parts.append(f"({self.expr(left)} {_CMP[type(op)]} {self.expr(right)})")
                left = right
            return "(" + " && ".join(parts) + ")"
        if isinstance(e, ast.BoolOp):
            op = " && " if isinstance(e.op, ast.And) else " || "
            return "(" + op.join(self.expr(v) for v in e.values) + ")"
        if isinstance(e, ast.IfExp):
            return f"({self.expr(e.test)} ? {self.expr(e.body)} : {self.expr(e.orelse)})"
        if isinstance(e, ast.Call):
            f = e.func
            name = (f.attr if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name)
                    and f.value.id == "np" else f.id if isinstance(f, ast.Name) else None)
            if name in _MATH and not (isinstance(f, ast.Name) and name != "abs"):
                wide = any(self.printer.ctype(self.type_of(a)) != "double" for a in e.args
                           if self.type_of(a) != "int")
                table = _CMATH if wide else _MATH
                return f"{table[name]}({', '.join(self.expr(a) for a in e.args)})"
            if isinstance(f, ast.Name) and f.id in self.printer.names:
                return f"{self.printer.c_name(f.id)}({', '.join(self.arg(a) for a in e.args)})"
            self.fail(e, f"call of {ast.unparse(f)}")
        self.fail(e, f"expression {ast.unparse(e)}")

    def _index(self, e):
        name = e.value.id if isinstance(e.value, ast.Name) else None
        if name not in self.arrays:
            self.fail(e, f"indexing {ast.unparse(e.value)}, not an array")
        idx = e.slice.elts if isinstance(e.slice, ast.Tuple) else [e.slice]
        for i in idx:
            if isinstance(i, ast.Slice):
                self.fail(e, "slices (index one element, or pass a row a[i])")
        shape = self.arrays[name]
        flat = self.expr(idx[0])
        for k in range(1, len(idx)):
            flat = f"({flat}) * {shape[k]} + {self.expr(idx[k])}"
        rest = shape[len(idx):]
        return name, flat, rest

    def subscript(self, e):
        name, flat, rest = self._index(e)
        if rest:
            self.fail(e, f"{ast.unparse(e)} is a row: only an argument may be one")
        return f"{name}[{flat}]"

    def arg(self, a):
        if isinstance(a, ast.Subscript):
            name, flat, rest = self._index(a)
            if rest:
                stride = " * ".join(rest)
                return f"&{name}[({flat}) * {stride}]"
            return f"{name}[{flat}]"
        return self.expr(a)

    # ---------------------------------------------------------------- statements
    def block(self, body, ind):
        out = []
        for s in body:
            out += self.stmt(s, ind)
        return out

    def stmt(self, s, ind):
        p = "    " * ind
        if isinstance(s, ast.Expr):
            if isinstance(s.value, ast.Constant):       # a docstring
                return []
            return [f"{p}{self.expr(s.value)};"]
        if isinstance(s, ast.Assign):
            t, v = s.targets[0], s.value
            if isinstance(t, ast.Name):
                if self._is_alloc(v):
                    return self.alloc(t.id, v, p)
                if isinstance(v, ast.Attribute) and v.attr == "dtype":
                    return []
                if t.id in self.sizes:
                    return []
                return [f"{p}{t.id} = {self.expr(v)};"]
            return [f"{p}{self.subscript(t)} = {self.expr(v)};"]
        if isinstance(s, ast.AugAssign):
            tgt = s.target.id if isinstance(s.target, ast.Name) else self.subscript(s.target)
            return [f"{p}{tgt} {_OPS[type(s.op)]}= {self.expr(s.value)};"]
        if isinstance(s, ast.For):
            it = s.iter
            if not (isinstance(it, ast.Call) and isinstance(it.func, ast.Name)
                    and it.func.id == "range" and not s.orelse):
                self.fail(s, "for over anything but range(...)")
            a = [self.expr(x) for x in it.args]
            start, stop, step = ("0", a[0], 1) if len(a) == 1 else (a[0], a[1], 1) \
                if len(a) == 2 else (a[0], a[1], ast.literal_eval(it.args[2]))
            v = s.target.id
            cond = f"{v} < {stop}" if step > 0 else f"{v} > {stop}"
            inc = f"{v} += {step}" if step != 1 else f"{v}++"
            inc = f"{v} -= {-step}" if step < 0 else inc
            return ([f"{p}for ({v} = {start}; {cond}; {inc}) {{"]
                    + self.block(s.body, ind + 1) + [f"{p}}}"])
        if isinstance(s, ast.While):
            return ([f"{p}while ({self.expr(s.test)}) {{"] + self.block(s.body, ind + 1)
                    + [f"{p}}}"])
        if isinstance(s, ast.If):
            out = [f"{p}if ({self.expr(s.test)}) {{"] + self.block(s.body, ind + 1)
            orelse = s.orelse
            while len(orelse) == 1 and isinstance(orelse[0], ast.If):
                out += [f"{p}}} else if ({self.expr(orelse[0].test)}) {{"]
                out += self.block(orelse[0].body, ind + 1)
                orelse = orelse[0].orelse
            if orelse:
                out += [f"{p}}} else {{"] + self.block(orelse, ind + 1)
            return out + [f"{p}}}"]
        if isinstance(s, ast.Break):
            return [f"{p}break;"]
        if isinstance(s, ast.Return):
            return [f"{p}return;" if s.value is None else f"{p}return {self.expr(s.value)};"]
        if isinstance(s, ast.Pass):
            return []
        self.fail(s, f"statement {type(s).__name__}")

    def alloc(self, name, v, p):
        shape = self.arrays[name]
        size = " * ".join(shape)
        if v.func.attr == "zeros":
            return [f"{p}for (int i_ = 0; i_ < {size}; i_++) {name}[i_] = 0.0;"]
        return []

    def declarations(self, body):
        text = "\n".join(body)
        out = []
        for name in self.locals:
            if name not in self.sizes and _uses(text, name):
                out.append(f"    {self.printer.ctype(self.scalars[name])} {name};")
        for name, shape in self.arrays.items():
            if name not in self.params_names() and _uses(text, name):
                out.append(f"    {self.printer.ctype(self.elems[name])} {name}"
                           f"[{' * '.join(shape)}];")
        return out

    def c(self):
        head = (f"static {self.ret or 'void'} {self.printer.c_name(self.name)}("
                + ", ".join(self.params) + ")")
        body = self.block(self.tree.body, 1)
        unused = [f"    (void){a};" for a in sorted(self.params_names())
                  if not any(_uses(ln, a) for ln in body)]
        return head, f"{head} {{\n" + "\n".join(unused + self.declarations(body) + body) + "\n}\n"


def _uses(text, name):
    import re
    return re.search(rf"(?<![A-Za-z0-9_]){re.escape(name)}(?![A-Za-z0-9_])", text) is not None


class _Printer:
    def __init__(self, kernels, prefix, real="double", suffix="", also=()):
        self.own = {fn.__name__ for fn in kernels}
        self.names = self.own | set(also)
        self.prefix = prefix
        self.real = real
        self.suffix = suffix
        # the return annotations (a string's text under ``from __future__ import annotations``)
        ann = {fn.__name__: fn.__annotations__.get("return") for fn in kernels}
        self.returns = {k: (v.strip("'\"") if isinstance(v, str) else None)
                        for k, v in ann.items()}
        self.returns.update({nm: None for nm in also})

    def dim(self, d):
        return d if d.isdigit() else f"{self.prefix.upper()}{d}"

    def ctype(self, kind):
        return {"int": "int", "float": "double", "real": self.real,
                "cplx": "double complex"}[kind]

    def c_name(self, name):
        if name in self.own:
            return f"{self.prefix}{name.lstrip('_')}{self.suffix}"
        return f"{self.prefix}{name.lstrip('_')}"


def print_kernels(kernels, prefix, printed=(), *, real="double", suffix="", also=()):
    """C99 text of the kernels (static functions named ``<prefix><name><suffix>``, in the
    given order, which must be the order of dependency): prototypes first, then
    definitions; `printed` are kernels printed elsewhere in the same file (callable by
    these), `also` names of other functions printed there (``<prefix><name>``).  `real` is
    the C type of ``real`` values: ``"double complex"`` prints the kernels for the complex
    step (the includer needs ``<complex.h>``)."""
    pr = _Printer(tuple(kernels) + tuple(printed), prefix, real=real, suffix=suffix, also=also)
    heads, bodies = [], []
    for fn in kernels:
        head, body = _Function(fn, pr).c()
        heads.append(head + ";")
        bodies.append(body)
    return "\n".join(heads) + "\n\n" + "\n".join(bodies)
