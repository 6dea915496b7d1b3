"""PDF report with matplotlib's PdfPages: text pages laid out by hand, then the figures.

No TeX: text is drawn with matplotlib's own fonts (TrueType, pdf.fonttype 42), so it
stays selectable and searchable.
"""
from __future__ import annotations

from functools import lru_cache

from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from matplotlib.textpath import TextToPath

from .content import ReportContent, Table

__all__ = ["TextPages", "write_text_pages", "PAGE_W", "PAGE_H"]

#: The PDF report's page size: A4, in inches.
PAGE_W, PAGE_H = 8.27, 11.69
MARGIN_X, MARGIN_TOP, MARGIN_BOTTOM = 0.7, 0.75, 0.75
EM = 0.56  # average glyph width of DejaVu Sans in em (only for the narrowest column)
_TEXT_TO_PATH = TextToPath()

_VERDICT_COLORS = {"PASS": ("#dff3e0", "#1b5e20"), "FAIL": ("#fde0dc", "#b71c1c"),
                   "HOLDS": ("#dff3e0", "#1b5e20"), "FAILS": ("#fde0dc", "#b71c1c"),
                   "NOT DECIDED": ("#fff4d6", "#7a5300")}
_MATH = [("𝒲", r"$\mathcal{W}$"), ("𝒴", r"$\mathcal{Y}$")]


def _tex(s: str) -> str:
    """Make text safe for matplotlib (mathtext only where DejaVu lacks the glyph)."""
    s = s.replace("$", r"\$")
    for a, b in _MATH:
        s = s.replace(a, b)
    return s


@lru_cache(maxsize=None)
def _width_in(s: str, size: float, bold: bool) -> float:
    """Width of `s` as drawn (DejaVu Sans, matplotlib's default), in inches: measured, so a
    bold header wraps where it really ends (an average glyph width let them collide)."""
    for a, _ in _MATH:
        s = s.replace(a, "W")
    prop = FontProperties(family="DejaVu Sans", size=size, weight="bold" if bold else "normal")
    w, _, _ = _TEXT_TO_PATH.get_text_width_height_descent(s, prop, ismath=False)
    return w / 72.0


def _wrap(text: str, width_in: float, size: float, bold: bool = False) -> list[str]:
    """Greedy word wrap of `text` to lines no wider than `width_in` inches."""
    width_in = max(width_in, 4 * EM * size / 72.0)
    lines: list[str] = []
    for para in str(text).split("\n"):
        line = ""
        for word in para.split():
            trial = f"{line} {word}" if line else word
            if _width_in(trial, size, bold) <= width_in:
                line = trial
                continue
            if line:
                lines.append(line)
            while _width_in(word, size, bold) > width_in and len(word) > 1:
                k = len(word) - 1          # a word wider than the column: break it
                while k > 1 and _width_in(word[:k], size, bold) > width_in:
                    k -= 1
                lines.append(word[:k])
                word = word[k:]
            line = word
        lines.append(line)
    return lines


def _longest_word(texts, size: float, bold: bool) -> float:
    return max((_width_in(w, size, bold) for s in texts for w in str(s).split()), default=0.0)


def column_widths(t: Table, width: float, size: float, pad: float) -> list[float]:
    """Column widths (inches) summing to `width`: the table's proportions, except that
    every column is at least as wide as its longest word (header words bold), so no word
    is broken ("metho d", "0.04217 99") while the other columns can give room.  Only when
    the longest words alone exceed `width` do the columns share it in their proportion."""
    total = sum(t.widths)
    want = [w / total * width for w in t.widths]
    need = [max(_longest_word([h], size, True), _longest_word([r[j] for r in t.rows], size,
                                                              False)) + 2 * pad + 0.01
            for j, h in enumerate(t.header)]
    if sum(need) > width:
        return [n / sum(need) * width for n in need]
    fixed = [False] * len(want)
    while True:      # pin the columns below their need, share the rest in proportion
        room = width - sum(n for n, f in zip(need, fixed) if f)
        free = sum(w for w, f in zip(want, fixed) if not f)
        widths = [n if f else w / free * room for n, w, f in zip(need, want, fixed)]
        short = [j for j, (w, n) in enumerate(zip(widths, need)) if not fixed[j] and w < n]
        if not short:
            return widths
        for j in short:
            fixed[j] = True


def plan_table_pages(heights, head_h, first_avail, page_avail):
    """Split the rows of a table over pages so that no page holds a lone row.

    ``heights``: row heights; ``head_h``: the header's (repeated on every page);
    ``first_avail``: room on the current page, ``page_avail``: on a fresh page (after the
    "(continued)" line).  Returns ``(new_page_first, groups)``: whether the table must start
    on a fresh page, and the row indices of each page.  A page never gets one row of a
    table of two or more rows (widow/orphan rows), and the header never stands alone;
    only a row taller than a whole page breaks these rules.
    """
    n = len(heights)
    if n == 0:
        return False, []

    def fit(start, avail):
        k, used = 0, head_h
        while start + k < n and used + heights[start + k] <= avail:
            used += heights[start + k]
            k += 1
        return k

    def split(avail):
        groups, start = [], 0
        while start < n:
            k = max(fit(start, avail), 1)
            if n - start - k == 1 and k >= 3:
                k -= 1                   # take one more row over: the last page gets two
            groups.append(list(range(start, start + k)))
            start += k
            avail = page_avail
        return groups

    def lone(groups):
        return n >= 2 and any(len(g) < 2 for g in groups)

    here = split(first_avail)
    if not lone(here):
        return False, here
    fresh = split(page_avail)
    if not lone(fresh) or len(fresh[0]) > len(here[0]):
        return True, fresh               # start the table on a new page
    return False, here                   # rows taller than a page: nothing better exists


class TextPages:
    """Flowing text and tables on A4 pages of a PdfPages document."""

    def __init__(self, pdf, footer: str = ""):
        self.pdf = pdf
        self.footer = footer
        self.fig: Figure | None = None
        self.y = 0.0
        self.pages = 0

    # page handling
    def new_page(self):
        self.flush()
        self.fig = Figure(figsize=(PAGE_W, PAGE_H))
        self.y = PAGE_H - MARGIN_TOP
        self.pages += 1

    def flush(self):
        if self.fig is not None:
            if self.footer:
                self._text(MARGIN_X, MARGIN_BOTTOM * 0.5, self.footer, 7, color="#777777")
            self.pdf.savefig(self.fig)
            self.fig = None

    def _ensure(self, height: float):
        if self.fig is None or self.y - height < MARGIN_BOTTOM:
            self.new_page()

    def _text(self, x, y, s, size, **kw):
        self.fig.text(x, y, _tex(s), fontsize=size, transform=self.fig.dpi_scale_trans,
                      va="top", ha="left", **kw)

    @staticmethod
    def _lh(size: float) -> float:
        return size * 1.32 / 72.0

    # content
    def space(self, inches: float):
        self.y -= inches

    def heading(self, text: str, size: float = 13):
        self._ensure(self._lh(size) * 3)  # keep with what follows
        self.y -= 0.08
        self._text(MARGIN_X, self.y, text, size, fontweight="bold")
        self.y -= self._lh(size) + 0.06

    def paragraph(self, text: str, size: float = 9, **kw):
        width = PAGE_W - 2 * MARGIN_X
        for line in _wrap(text, width, size, kw.get("fontweight") == "bold"):
            self._ensure(self._lh(size))
            self._text(MARGIN_X, self.y, line, size, **kw)
            self.y -= self._lh(size)
        self.y -= 0.05

    def table(self, t: Table, size: float = 8):
        width = PAGE_W - 2 * MARGIN_X
        lh = self._lh(size)
        pad = 0.04
        colw = column_widths(t, width, size, pad)

        def row_lines(cells, bold=False):
            return [_wrap(c, w - 2 * pad, size, bold) for c, w in zip(cells, colw)]

        def draw_row(cells, *, bold=False, shade=None):
            lines = row_lines(cells, bold)
            h = max(len(x) for x in lines) * lh + 2 * pad
            x = MARGIN_X
            if shade:
                self.fig.add_artist(Rectangle((MARGIN_X, self.y - h), width, h, facecolor=shade,
                                              edgecolor="none", transform=self.fig.dpi_scale_trans))
            for j, (cell_lines, w) in enumerate(zip(lines, colw)):
                kw = {"fontweight": "bold"} if bold else {}
                if t.verdict_col == j and not bold:
                    bg, fg = _VERDICT_COLORS.get(cells[j], ("#eeeeee", "#444444"))
                    self.fig.add_artist(Rectangle((x, self.y - h), w, h, facecolor=bg, edgecolor="none",
                                                  transform=self.fig.dpi_scale_trans))
                    kw = {"fontweight": "bold", "color": fg}
                yy = self.y - pad
                for line in cell_lines:
                    self._text(x + pad, yy, line, size, **kw)
                    yy -= lh
                x += w
            self.y -= h
            self.fig.add_artist(Line2D([MARGIN_X, MARGIN_X + width], [self.y, self.y], lw=0.4,
                                       color="#bbbbbb", transform=self.fig.dpi_scale_trans))

        def header():
            self.fig.add_artist(Line2D([MARGIN_X, MARGIN_X + width], [self.y, self.y], lw=0.8,
                                       color="#555555", transform=self.fig.dpi_scale_trans))
            draw_row(t.header, bold=True, shade="#eeeeee")

        head_h = max(len(x) for x in row_lines(t.header, True)) * lh + 2 * pad
        heights = [max(len(x) for x in row_lines(row)) * lh + 2 * pad for row in t.rows]
        if not t.rows:  # empty table
            self.heading(t.title, 11)
            self.paragraph("(no rows)")
        else:
            title_h = self._lh(11) * 3           # what heading() reserves
            cont_h = self._lh(9) + 0.04
            full = PAGE_H - MARGIN_TOP - MARGIN_BOTTOM
            if self.fig is None:
                self.new_page()
            first_avail = self.y - MARGIN_BOTTOM - title_h
            new_first, groups = plan_table_pages(heights, head_h, first_avail, full - cont_h)
            if new_first:
                self.new_page()
                first_avail = self.y - MARGIN_BOTTOM - title_h
                groups = plan_table_pages(heights, head_h, first_avail, full - cont_h)[1]
            self.heading(t.title, 11)
            for g, rows in enumerate(groups):
                if g > 0:
                    self.new_page()
                    self._text(MARGIN_X, self.y, t.title + " (continued)", 9, fontstyle="italic")
                    self.y -= cont_h
                header()
                for i in rows:
                    draw_row(t.rows[i])
            self.rows_per_page = getattr(self, "rows_per_page", {})
            self.rows_per_page[t.key] = [len(rows) for rows in groups]
        if t.note:
            self.y -= 0.04
            self.paragraph(t.note, 7.5, color="#555555")
        self.y -= 0.12


def write_text_pages(pdf, content: ReportContent, figure_titles: list[str]) -> int:
    """Title page with the conclusions, then the other tables; returns the page count."""
    c = content
    tp = TextPages(pdf, footer=f"{c.title}  ·  {dict(c.meta).get('generated', '')}")
    tp.new_page()
    tp.space(0.3)
    tp._text(MARGIN_X, tp.y, c.title, 20, fontweight="bold")
    tp.y -= tp._lh(20) + 0.05
    tp.paragraph(c.subtitle, 10.5, fontstyle="italic")
    tp.space(0.1)
    if c.synthetic:
        tp.paragraph("SYNTHETIC DATA: the curves of this report are made up to test its layout; "
                     "they are not simulation results.", 10, color="#b71c1c", fontweight="bold")
    for label, value in c.meta:
        if label == "DATA":
            continue
        tp._ensure(tp._lh(9))
        tp._text(MARGIN_X, tp.y, label, 9, color="#555555")
        for k, line in enumerate(_wrap(value, PAGE_W - 2 * MARGIN_X - 1.7, 9)):
            tp._text(MARGIN_X + 1.6, tp.y, line, 9)
            tp.y -= tp._lh(9)
    tp.space(0.15)
    tables = {t.key: t for t in c.tables}
    order = ["conclusions", "summary"] + [t.key for t in c.tables if t.key not in ("conclusions", "summary")]
    for i, key in enumerate(order):
        if key not in tables:
            continue
        if key == "parameters":
            tp.new_page()
        tp.table(tables[key])
        if key == "summary" and figure_titles:
            # the list of figures stays on one page (it was split after its first lines)
            tp._ensure(tp._lh(11) * 3 + len(figure_titles) * (tp._lh(9) + 0.05))
            tp.heading("Figures", 11)
            for title in figure_titles:
                tp.paragraph(title, 9)
    tp.flush()
    return tp.pages
