"""Report writers: PDF (reportlab), self-contained HTML (inline PNG), CSV (directory or zip).

Sections (PDF pages, HTML sections): Summary, Usage, Load spectrum, Damage and remaining life,
Duty record, Events, Productivity, Assumptions, and Service schedule for a stored machine.
CSV files: ``summary.csv``, ``usage.csv``, ``spectra.csv``, ``assumptions.csv``,
``cycles.csv`` (rainflow from-to table), ``damage.csv``, ``duty.csv``, ``events.csv``,
``work_cycles.csv`` (and ``schedule.csv``); written into a directory, or a ``.zip`` if the
output name ends in .zip.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cranetwin.analytics import AnalyticsReport
from cranetwin.errors import MissingExtraError, ReportError
from cranetwin.model import Machine
from cranetwin.reports import tables as T

FORMATS = ("pdf", "html", "csv")
MAX_EVENT_ROWS = 200  # in the PDF and HTML; the CSV has all

SECTIONS = ("Summary", "Usage", "Load spectrum", "Damage and remaining life", "Duty record",
            "Events", "Productivity", "Assumptions")


Schedule = Sequence[Any] | None
"""The machine's service schedule (:class:`cranetwin.service.schedules.DueStatus` per item), or
None when the report is not of a stored machine (no section then)."""


def _sections(rep: AnalyticsReport, machine: Machine, source: str, figs: dict[str, bytes],
              schedule: Schedule = None) -> list[tuple[str, str, list[T.Table], bytes | None]]:
    """(heading, intro, tables, figure) per section."""
    ev = T.events(rep, MAX_EVENT_ROWS)
    n_ev = len(rep.events)
    extra = [] if schedule is None else [
        ("Service schedule", "Maintenance items by operating hours, lifts (work cycles), "
         "Miner damage of a fatigue detail or calendar days, counted over the machine's whole "
         "processed history (not only this report's range); due dates estimated from the "
         "last 7 days' rate. Due: within 10 % of the interval; overdue: past it.",
         [T.schedule(schedule)], None)]
    return [
        ("Summary", f"Load-history report of {machine.name}: {machine.machine.description}.",
         [T.summary(rep, machine, source)], None),
        ("Usage", "Time is counted only while the machine sends data. Working: a joint moves "
         "faster than 3 % of its velocity limit; pauses under 30 s count as working.",
         [T.usage(rep)], figs.get("usage")),
        ("Load spectrum", "Rainflow cycle counting per ASTM E1049 (residue as half cycles) of "
         "the cylinder forces and joint reaction moments.", [T.spectra(rep)],
         figs.get("spectrum")),
        ("Damage and remaining life", "Palmgren-Miner sum D = Σ n_i/N_i with "
         "N = 2·10⁶·(Δσc/Δσ)^m (EN 13001-3-1). Remaining life and the next service (next "
         "multiple of the inspection step of D) at the damage rate of the rate basis (see the "
         "Summary and Assumptions), counted from the end of the requested range.",
         [T.damage(rep, machine)], figs.get("damage")),
        ("Duty record", "Crane classification per ISO 4301-1 / FEM 1.001 and the used design "
         "working period per ISO 12482 (recording method a).", [T.duty(rep)], None),
        ("Events", f"{n_ev} events" + (f" (first {MAX_EVENT_ROWS} listed; all in the CSV)"
                                       if n_ev > MAX_EVENT_ROWS else "") + ".",
         [ev], figs.get("events")),
        ("Productivity", "Work cycles: grab (payload above 50 kg) → lift → swing → release.",
         [T.productivity(rep)], figs.get("productivity")),
        ("Assumptions", "Every figure of this report rests on these assumptions; results scale "
         "with the fatigue details and the design class.", [T.assumptions(rep)], None),
        *extra,
    ]


def check_format(fmt: str) -> None:
    """Check, before any work, that a report in ``fmt`` can be written here.

    Raises:
        ReportError: Unknown format.
        MissingExtraError: PDF or HTML without the ``reports`` extra (matplotlib draws the
            figures of both, reportlab writes the PDF).
    """
    if fmt not in FORMATS:
        raise ReportError(f"unknown format {fmt!r}; expected one of {FORMATS}")
    if fmt == "csv":
        return
    try:
        import matplotlib  # noqa: F401

        if fmt == "pdf":
            import reportlab  # type: ignore[import-untyped]  # noqa: F401
    except ImportError as exc:
        raise MissingExtraError("reports", f"{fmt.upper()} reports") from exc


# --- PDF ------------------------------------------------------------------------------------------

def _col_widths(tab: T.Table, width: float) -> list[float]:
    """Column widths proportional to the longest text of each column (9 to 50 characters)."""
    cols = list(zip(tab.header, *tab.rows, strict=True))
    chars = [min(max(9, *(len(str(c)) for c in col)), 50) for col in cols]
    total = float(sum(chars))
    return [width * c / total for c in chars]


def _font() -> str:
    """Register DejaVu Sans (shipped with matplotlib; covers Σ, Δ, σ) and return its name."""
    from pathlib import Path as _P

    try:
        import matplotlib
        from reportlab.pdfbase import pdfmetrics  # type: ignore[import-untyped]
        from reportlab.pdfbase.ttfonts import TTFont  # type: ignore[import-untyped]
    except ImportError as exc:
        raise MissingExtraError("reports", "PDF reports") from exc

    if "DejaVuSans" not in pdfmetrics.getRegisteredFontNames():
        d = _P(matplotlib.get_data_path()) / "fonts" / "ttf"
        pdfmetrics.registerFont(TTFont("DejaVuSans", str(d / "DejaVuSans.ttf")))
        pdfmetrics.registerFont(TTFont("DejaVuSans-Bold", str(d / "DejaVuSans-Bold.ttf")))
    return "DejaVuSans"


def write_pdf(rep: AnalyticsReport, machine: Machine, out: Path, source: str,
              figs: dict[str, bytes], progress: Callable[[], None] | None = None,
              schedule: Schedule = None) -> Path:
    """PDF with one page per section (plots and tables).

    Raises:
        MissingExtraError: reportlab or matplotlib is not installed (``cranetwin[reports]``).
    """
    try:
        from reportlab.lib import colors  # type: ignore[import-untyped]
        from reportlab.lib.pagesizes import A4  # type: ignore[import-untyped]
        from reportlab.lib.styles import (  # type: ignore[import-untyped]
            ParagraphStyle,
            getSampleStyleSheet,
        )
        from reportlab.lib.units import mm  # type: ignore[import-untyped]
        from reportlab.platypus import (  # type: ignore[import-untyped]
            Image,
            LongTable,
            PageBreak,
            Paragraph,
            SimpleDocTemplate,
            Spacer,
            TableStyle,
        )
    except ImportError as exc:
        raise MissingExtraError("reports", "PDF reports") from exc

    font = _font()
    ss = getSampleStyleSheet()
    h1 = ParagraphStyle("h1", parent=ss["Heading1"], fontName=font + "-Bold")
    body = ParagraphStyle("b", parent=ss["BodyText"], fontName=font, fontSize=9)
    cell = ParagraphStyle("c", parent=body, fontSize=6.5, leading=7.5)
    width = A4[0] - 30 * mm
    story: list[object] = []
    for i, (head, intro, tabs, fig) in enumerate(_sections(rep, machine, source, figs,
                                                           schedule)):
        if i:
            story.append(PageBreak())
        story += [Paragraph(head, h1), Paragraph(html.escape(intro), body), Spacer(1, 3 * mm)]
        if fig is not None:
            img = Image(io.BytesIO(fig))
            scale = width / img.imageWidth
            img.drawWidth, img.drawHeight = width, img.imageHeight * scale
            story += [img, Spacer(1, 3 * mm)]
        for tab in tabs:
            data = [[Paragraph(html.escape(str(c)), cell) for c in tab.header]]
            data += [[Paragraph(html.escape(str(c)), cell) for c in r] for r in tab.rows]
            if len(data) == 1:
                story.append(Paragraph("(none)", body))
                continue
            t = LongTable(data, repeatRows=1, colWidths=_col_widths(tab, width))
            t.setStyle(TableStyle([
                ("GRID", (0, 0), (-1, -1), 0.25, colors.grey),
                ("BACKGROUND", (0, 0), (-1, 0), colors.HexColor("#dde6f0")),
                ("VALIGN", (0, 0), (-1, -1), "TOP")]))
            story.append(t)
        if progress:
            progress()
    doc = SimpleDocTemplate(str(out), pagesize=A4, leftMargin=15 * mm, rightMargin=15 * mm,
                            topMargin=15 * mm, bottomMargin=15 * mm,
                            title=f"cranetwin report {machine.name}", author="cranetwin")
    doc.build(story)
    return out


# --- HTML -----------------------------------------------------------------------------------------

CSS = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
table{border-collapse:collapse;font-size:12px;margin:.5em 0 1.5em}td,th{border:1px solid #bbb;
padding:2px 6px}th{background:#dde6f0}img{max-width:100%}section{margin-bottom:2em}"""


def write_html(rep: AnalyticsReport, machine: Machine, out: Path, source: str,
               figs: dict[str, bytes], progress: Callable[[], None] | None = None,
               schedule: Schedule = None) -> Path:
    """One self-contained HTML file (inline CSS and base64 PNG figures, no external links)."""
    parts = [f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>cranetwin "
             f"report {html.escape(machine.name)}</title><style>{CSS}</style></head><body>"]
    for head, intro, tabs, fig in _sections(rep, machine, source, figs, schedule):
        parts.append(f"<section><h1>{html.escape(head)}</h1><p>{html.escape(intro)}</p>")
        if fig is not None:
            b64 = base64.b64encode(fig).decode("ascii")
            parts.append(f"<img alt='{html.escape(head)}' src='data:image/png;base64,{b64}'>")
        for tab in tabs:
            parts.append(f"<table><caption>{html.escape(tab.title)}</caption><tr>"
                         + "".join(f"<th>{html.escape(h)}</th>" for h in tab.header) + "</tr>")
            for r in tab.rows:
                parts.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r)
                             + "</tr>")
            parts.append("</table>")
        parts.append("</section>")
        if progress:
            progress()
    parts.append("</body></html>")
    out.write_text("\n".join(parts), encoding="utf-8")
    return out


# --- CSV ------------------------------------------------------------------------------------------

def csv_tables(rep: AnalyticsReport, machine: Machine, source: str,
               schedule: Schedule = None) -> dict[str, T.Table]:
    """The CSV files and their tables."""
    extra = {} if schedule is None else {"schedule.csv": T.schedule(schedule)}
    return {"summary.csv": T.summary(rep, machine, source), "usage.csv": T.usage(rep),
            "spectra.csv": T.spectra(rep), "cycles.csv": T.cycle_rows(rep),
            "damage.csv": T.damage(rep, machine), "duty.csv": T.duty(rep),
            "events.csv": T.events(rep), "work_cycles.csv": T.work_cycles(rep),
            "assumptions.csv": T.assumptions(rep), **extra}


def _csv_text(tab: T.Table) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(tab.header)
    w.writerows(tab.rows)
    return buf.getvalue()


def write_csv(rep: AnalyticsReport, machine: Machine, out: Path, source: str,
              schedule: Schedule = None) -> Path:
    """CSV files into directory ``out`` (created), or into a zip archive if ``out`` ends .zip."""
    files = {name: _csv_text(t) for name, t in csv_tables(rep, machine, source,
                                                          schedule).items()}
    if out.suffix.lower() == ".zip":
        with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as z:
            for name, text in files.items():
                z.writestr(name, text)
        return out
    if out.exists() and not out.is_dir():
        raise ReportError(f"{out} exists and is not a directory; CSV output is a directory "
                          "or a .zip file")
    out.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (out / name).write_text(text, encoding="utf-8")
    return out


def write(rep: AnalyticsReport, machine: Machine, fmt: str, out: Path, source: str,
          progress: Callable[[], None] | None = None, schedule: Schedule = None) -> Path:
    """Write the report in ``fmt`` (pdf, html or csv) to ``out`` (with a Service schedule
    section when ``schedule`` is given).

    Raises:
        ReportError: Unknown format or the file could not be written.
        MissingExtraError: PDF or HTML without the ``reports`` extra installed.
    """
    check_format(fmt)
    try:
        if fmt == "csv":
            return write_csv(rep, machine, out, source, schedule)
        from cranetwin.reports.figures import all_figures

        figs = all_figures(rep, machine)
        if fmt == "pdf":
            return write_pdf(rep, machine, out, source, figs, progress, schedule)
        return write_html(rep, machine, out, source, figs, progress, schedule)
    except OSError as exc:
        raise ReportError(f"cannot write {out}: {exc}") from exc


MEDIA_TYPES = {"pdf": "application/pdf", "html": "text/html; charset=utf-8",
               "csv": "application/zip"}


def render(rep: AnalyticsReport, machine: Machine, fmt: str, source: str,
           schedule: Schedule = None) -> tuple[bytes, str, str]:
    """The report as bytes for a download (e.g. from the API): ``(content, media type, file
    name)``; CSV comes as a zip of the CSV files.

    Raises:
        ReportError: Unknown format or the report could not be produced.
        MissingExtraError: PDF or HTML without the ``reports`` extra installed.
    """
    import tempfile

    check_format(fmt)
    name = f"{machine.name}-report.{'zip' if fmt == 'csv' else fmt}"
    with tempfile.TemporaryDirectory() as d:
        path = write(rep, machine, fmt, Path(d) / name, source, schedule=schedule)
        return path.read_bytes(), MEDIA_TYPES[fmt], name
