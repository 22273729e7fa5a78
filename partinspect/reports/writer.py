"""Write report.json, junit.xml and report.html into the output folder."""

import json

from partinspect.atomic import write_text_atomic

REPORT_FILES = ("report.json", "junit.xml", "report.html")


def report_json(report):
    """report.json text: indented, key order kept, NaN refused (not JSON)."""
    return json.dumps(report, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def write_reports(out_dir, report):
    """Render all three outputs first, then write each atomically.

    Rendering everything before writing anything means a failure in one
    renderer leaves the previous reports untouched.
    """
    from partinspect.reports.html import render_html
    from partinspect.reports.junit import junit_xml

    texts = {"report.json": report_json(report), "junit.xml": junit_xml(report), "report.html": render_html(report)}
    for name in REPORT_FILES:
        write_text_atomic(out_dir / name, texts[name])
    return [out_dir / name for name in REPORT_FILES]
