"""Write report.json, junit.xml and report.html into the output folder."""

import json

from partinspect.atomic import write_files_atomic

REPORT_FILES = ("report.json", "junit.xml", "report.html")


def report_json(report):
    """report.json text: indented, key order kept, NaN refused (not JSON)."""
    return json.dumps(report, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def render_reports(report, figures=None):
    """report.json, junit.xml and report.html as text, keyed by file name.

    ``figures`` is the optional dict of run data for the HTML report's
    figures (images, overlays, residuals, 3D points, CAD edges; the exact
    interface is in :mod:`partinspect.reports.figures`); it does not change
    report.json or junit.xml.
    """
    from partinspect.reports.html import render_html
    from partinspect.reports.junit import junit_xml

    return {"report.json": report_json(report), "junit.xml": junit_xml(report), "report.html": render_html(report, figures)}


def write_texts(out_dir, texts):
    """The rendered reports written into ``out_dir``, replaced together.

    An interrupt never leaves a report.json of this run beside a report.html
    of the last (`partinspect.atomic.write_files_atomic`).
    """
    return write_files_atomic({out_dir / name: texts[name].encode("utf-8") for name in REPORT_FILES})


def write_reports(out_dir, report, figures=None):
    """Render all three outputs first, then write each atomically.

    Rendering everything before writing anything means a failure in one
    renderer leaves the previous reports untouched.
    """
    return write_texts(out_dir, render_reports(report, figures))
