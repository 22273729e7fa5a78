"""report.html in a real browser: headless Chromium opens it from disk.

Chromium is driven over its DevTools pipe (``tests/reports/cdp.py``, stdlib
only): console errors, uncaught exceptions, CSP violations and every request
are collected; the page's layout is read from the live DOM; a screenshot and
an A4 print are taken. Chromium comes from ``scripts/install.sh`` (``make
test`` installs it); when it is missing the test tries that script once and
skips, saying why, only when Chromium truly cannot be installed.
"""

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from partinspect.reports.writer import write_reports
from tests.reports.cdp import Browser, find_chromium
from tests.reports.synthetic import CHARS, char, make_figures, make_report

REPO = Path(__file__).resolve().parents[2]
FAIL_RGB = (179, 38, 30)  # --fail in _style.css.j2, the FAIL badge


@pytest.fixture(scope="module")
def chromium():
    path = find_chromium()
    if path is None:
        try:
            r = subprocess.run(["bash", str(REPO / "scripts" / "install.sh"), "--browser-only"],
                               capture_output=True, text=True, timeout=900)
            why = (r.stderr.strip().splitlines() or ["no message"])[-1]
        except (OSError, subprocess.TimeoutExpired) as exc:
            why = str(exc)
        path = find_chromium()
        if path is None:
            pytest.skip(f"Chromium is not installed and could not be installed ({why})")
    return path


@pytest.fixture(scope="module")
def browser(chromium, tmp_path_factory):
    b = Browser(chromium, tmp_path_factory.mktemp("chromium-profile"), width=1280, height=900)
    yield b
    b.close()


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    write_reports(out, make_report(), make_figures(seed=4))
    return out


def _loaded(browser, path):
    browser.open(path.resolve().as_uri())
    assert browser.errors() == []
    outside = [u for u in browser.requests() if not u.startswith(("file:", "data:"))]
    assert outside == [], f"the report fetched {outside}"


def test_report_opens_clean_and_shows_verdict_and_tables(browser, report_dir):
    _loaded(browser, report_dir / "report.html")
    page = browser.evaluate("""(() => {
        const v = document.getElementById('verdict'), r = v.getBoundingClientRect();
        const rows = [...document.querySelectorAll('#characteristics tbody tr')];
        const imgs = [...document.querySelectorAll('img')];
        const photos = [...document.querySelectorAll('svg.photo image')];
        return {
          verdict: v.textContent.trim(), visible: r.width > 0 && r.height > 0 && r.top >= 0 && r.bottom <= innerHeight,
          badge: getComputedStyle(v).backgroundColor,
          decisions: rows.map(t => t.dataset.decision), ids: rows.map(t => t.cells[0].innerText.split('\\n')[0]),
          tableVisible: document.getElementById('characteristics').getBoundingClientRect().height > 100,
          bars: document.querySelectorAll('#characteristics svg.tolbar').length,
          figures: [...document.querySelectorAll('figure')].map(f => f.id),
          imgsLoaded: imgs.length > 0 && imgs.every(i => i.complete && i.naturalWidth > 0),
          photos: photos.length,
          viewer: document.getElementById('viewer3d').dataset.ready,
          features: document.querySelectorAll('#features tbody tr').length,
          width: document.documentElement.scrollWidth,
        };
    })()""")
    assert page["verdict"].lower() == "fail" and page["visible"]
    assert page["badge"] == "rgb({}, {}, {})".format(*FAIL_RGB)
    order = {"fail": 0, "inconclusive": 1, "pass": 2}
    assert page["decisions"] == sorted(page["decisions"], key=order.get) and page["decisions"][0] == "fail"
    assert sorted(page["ids"]) == sorted(c["id"] for c in CHARS)
    assert page["tableVisible"] and page["bars"] == len(CHARS)
    assert page["figures"] == ["fig-images", "fig-residuals", "fig-sigmas", "fig-scene"]
    assert page["imgsLoaded"] and page["photos"] == 2
    assert page["viewer"] == "1"  # the report's script ran: its CSP hash matches
    assert page["features"] == 9
    assert page["width"] <= 1280  # nothing overflows sideways


def test_screenshot_is_not_blank_and_shows_the_badge(browser, report_dir, tmp_path):
    import cv2

    _loaded(browser, report_dir / "report.html")
    shot = browser.screenshot(tmp_path / "report.png", full_page=False)
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[:2] == (900, 1280)
    assert img.std() > 20  # text, tables, a badge: far from a blank page
    b, g, r = (img[..., i].astype(int) for i in range(3))
    badge = (abs(r - FAIL_RGB[0]) < 6) & (abs(g - FAIL_RGB[1]) < 6) & (abs(b - FAIL_RGB[2]) < 6)
    assert badge.sum() > 2000  # the FAIL badge's red, a block of it
    ys, xs = np.nonzero(badge)
    assert xs.mean() > 640 and ys.mean() < 200  # top right, where the verdict belongs


def test_3d_viewer_rotates_and_zooms(browser, report_dir):
    _loaded(browser, report_dir / "report.html")
    box = browser.evaluate("""(() => {
        const c = document.querySelector('#viewer3d canvas'); c.scrollIntoView({block: 'center'});
        const r = c.getBoundingClientRect(); return [r.left, r.top, r.width, r.height];
    })()""")
    snap = "document.querySelector('#viewer3d canvas').toDataURL()"
    ink = """(() => { const c = document.querySelector('#viewer3d canvas'), d = c.getContext('2d')
        .getImageData(0, 0, c.width, c.height).data; let n = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] < 200 || d[i + 1] < 200 || d[i + 2] < 200) n++; return n; })()"""
    before, drawn = browser.evaluate(snap), browser.evaluate(ink)
    assert drawn > 2000  # edges, points and ellipsoids were drawn
    x, y = box[0] + box[2] / 2, box[1] + box[3] / 2
    mouse = lambda kind, px, **kw: browser.call("Input.dispatchMouseEvent", {"type": kind, "x": px, "y": y, **kw},
                                                session=True)
    mouse("mouseMoved", x)
    mouse("mousePressed", x, button="left", buttons=1, clickCount=1)
    for dx in (20, 40, 60, 80):
        mouse("mouseMoved", x + dx, button="left", buttons=1)
    mouse("mouseReleased", x + 80, button="left", clickCount=1)
    rotated = browser.evaluate(snap)
    assert rotated != before
    mouse("mouseWheel", x, deltaX=0, deltaY=-400)
    assert browser.evaluate(snap) != rotated
    browser.evaluate("document.querySelector('#viewer3d button[data-view=\"iso\"]').click()")
    assert browser.evaluate(snap) == before  # the first view again, framed as at load
    assert browser.errors() == []


def test_prints_on_a4(browser, report_dir, tmp_path):
    _loaded(browser, report_dir / "report.html")
    pdf = browser.pdf(tmp_path / "report.pdf").read_bytes()
    assert pdf.startswith(b"%PDF")
    boxes = re.findall(rb"/MediaBox\s*\[\s*0 0 ([0-9.]+) ([0-9.]+)\s*\]", pdf)
    assert boxes and all(abs(float(w) - 595.3) < 2 and abs(float(h) - 841.9) < 2 for w, h in boxes)  # A4 in pt
    assert 2 <= len(boxes) <= 12  # tables, then the figures from a new page
    # Nothing wider than A4's printable width (210 mm - 2 x 14 mm margins = 688 CSS px) in print layout.
    browser.call("Emulation.setEmulatedMedia", {"media": "print"}, session=True)
    browser.call("Emulation.setDeviceMetricsOverride", {"width": 688, "height": 1000, "deviceScaleFactor": 1,
                                                        "mobile": False}, session=True)
    try:
        _loaded(browser, report_dir / "report.html")
        assert browser.evaluate("document.documentElement.scrollWidth") <= 688
        assert browser.evaluate("getComputedStyle(document.querySelector('.viewer-bar')).display") == "none"
    finally:
        browser.call("Emulation.setEmulatedMedia", {"media": ""}, session=True)
        browser.call("Emulation.setDeviceMetricsOverride", {"width": 1280, "height": 900, "deviceScaleFactor": 1,
                                                            "mobile": False}, session=True)


def test_hostile_strings_stay_text_and_a_bare_report_works(browser, tmp_path):
    nasty = '<img src=x onerror="window.__pwned=1"><script>window.__pwned=2</script>'
    chars = [char("circle-1.diameter", "pass", 4.004, 4.0, 3.95, 4.05, 0.008),
             char(f"{nasty}.diameter", "inconclusive", None, 12.0, 11.9, 12.1, reason=nasty)]
    report = make_report(chars, part=nasty, verdict="inconclusive", registration=False)
    report["inputs"][0]["path"] = f"/parts/{nasty}.step"
    figures = {"points3d": [{"label": nasty, "points": np.zeros((4, 3)), "covs": np.tile(np.eye(3) * 1e-6, (4, 1, 1)),
                             "status": "inconclusive"}]}
    write_reports(tmp_path, report, figures)
    _loaded(browser, tmp_path / "report.html")
    got = browser.evaluate("""(() => ({
        pwned: window.__pwned === undefined ? null : window.__pwned,
        title: document.getElementById('part').textContent,
        scripts: document.scripts.length,
        notes: [...document.querySelectorAll('.figure-note')].length,
        registration: !!document.getElementById('registration'),
        verdict: document.getElementById('verdict').textContent.trim(),
    }))()""")
    assert got["pwned"] is None and got["title"] == nasty
    assert got["scripts"] == 2  # the scene data and the report's own script, nothing injected
    assert got["notes"] == 2 and not got["registration"]  # no images, no residuals and got["verdict"].lower() == "inconclusive"
    # And with no figures at all: the page's script must not trip over the missing viewer.
    write_reports(tmp_path, make_report(verdict="fail"))
    _loaded(browser, tmp_path / "report.html")
