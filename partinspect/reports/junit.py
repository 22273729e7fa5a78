"""junit.xml: one test case per characteristic, so CI systems show them.

A failing characteristic is a ``<failure>``, an inconclusive one is
``<skipped>`` with its reason; the numbers (measured value, U, nominal,
limits, unit) are in the message. The suite's ``<properties>`` carry the
verdict, the part and the report schema; its ``<system-out>`` the one-line
summary. The file validates against ``schemas/junit.xsd`` (the structure of
the Jenkins xunit plugin's "junit-10" schema): in particular the
``<testsuites>`` root carries no ``skipped`` count, which that schema does
not allow there (the ``<testsuite>`` does).

References
----------
.. [1] The JUnit XML format as read by Jenkins, GitLab and GitHub Actions
       (the "junit-10" XSD of the Jenkins xunit plugin).
"""

import xml.etree.ElementTree as ET

JUNIT_XSD = "schemas/junit.xsd"  # package resource of partinspect.reports


def _fmt(x, digits=4):
    return "n/a" if x is None else f"{x:.{digits}f}"


def characteristic_message(c):
    """One line with the numbers of a characteristic, for CI logs."""
    unit = c.get("unit") or "mm"
    limits = f"limits [{_fmt(c.get('lower_limit'))}, {_fmt(c.get('upper_limit'))}] {unit}"
    if c.get("measured") is None:
        return f"{c['id']}: {c.get('reason') or 'not measured'}; nominal {_fmt(c.get('nominal'))}, {limits}"
    text = (
        f"{c['id']}: measured {_fmt(c['measured'])} +- {_fmt(c.get('expanded_uncertainty'))} (U, k=2), "
        f"nominal {_fmt(c.get('nominal'))}, {limits}: {c['decision']}"
    )
    if c["decision"] != "pass" and c.get("reason"):
        text += f" ({c['reason']})"
    return text


def _details(c):
    """The failure's body: message plus where the limits and the uncertainty came from."""
    lines = [characteristic_message(c)]
    if c.get("deviation") is not None:
        lines.append(f"deviation {c['deviation']:+.4f} {c.get('unit') or 'mm'}")
    if c.get("rule") or c.get("source"):
        lines.append(f"tolerance from {c.get('rule') or c.get('source')}")
    d, m = c.get("details") or {}, c.get("material")
    if m and d.get("bonus") is not None:
        lines.append(f"at {m['modifier']}: position {d['position']:.4f} - bonus {d['bonus']:.4f} (measured size "
                     f"{d['measured_size']:.4f}, {d['size_at_condition']:.4f} at {m['modifier']})")
    shift = d.get("datum_shift")
    if shift and shift.get("applied"):
        lines.append(f"datum shift ({shift['datums']}): moved {shift['translation']:.4f} mm, turned "
                     f"{shift['rotation_deg']:.4f} deg; {d['without_shift']:.4f} without it")
    elif shift:
        lines.append(f"{shift['datums']}: no datum shift applied ({shift['reason']})")
    if c.get("method"):
        lines.append(f"uncertainty: {c['method']}")
    return "\n".join(lines)


def junit_xml(report):
    """The junit.xml text for a report.json dict."""
    chars = report["characteristics"]
    suite_name = report["part"]
    cases = []
    for c in chars:
        case = ET.Element("testcase", classname=f"{suite_name}.{c.get('feature') or c['id']}", name=c["id"], time="0")
        if c["decision"] == "fail":
            ET.SubElement(case, "failure", message=characteristic_message(c), type="out of tolerance").text = _details(c)
        elif c["decision"] != "pass":
            ET.SubElement(case, "skipped", message=characteristic_message(c))
        cases.append(case)
    if not cases:
        # An empty suite would read as "all green" in some CI systems.
        case = ET.Element("testcase", classname=suite_name, name="inspection", time="0")
        ET.SubElement(case, "skipped", message=f"no characteristic could be evaluated; verdict {report['verdict']}")
        cases.append(case)
    failures = sum(c.find("failure") is not None for c in cases)
    skipped = sum(c.find("skipped") is not None for c in cases)
    counts = dict(tests=str(len(cases)), failures=str(failures), errors="0", time="0")
    root = ET.Element("testsuites", name="partinspect", **counts)
    suite = ET.SubElement(root, "testsuite", name=suite_name, skipped=str(skipped), **counts)
    if report.get("created"):
        suite.set("timestamp", report["created"][:19])
    props = ET.SubElement(suite, "properties")
    for name, value in (("verdict", report["verdict"]), ("part", report["part"]), ("schema", report.get("schema", ""))):
        ET.SubElement(props, "property", name=name, value=str(value))
    suite.extend(cases)
    summary = report.get("summary") or {}
    ET.SubElement(suite, "system-out").text = (
        f"{report['verdict'].upper()}: {summary.get('pass', 0)} pass, {summary.get('fail', 0)} fail, "
        f"{summary.get('inconclusive', 0)} inconclusive of {len(chars)} characteristics"
    )
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
