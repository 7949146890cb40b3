"""The report in a real browser (headless Chromium): it loads from file:// without a
console error, a failed load or a broken image, requests nothing but local files, and
its table sort and method comparison work. A full-page screenshot is kept
(``$COBGS_REPORT_SCREENSHOT`` names where; default: the test's temporary folder)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from report_browser import CHROMIUM, Browser

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).exists(),
    reason=f"{CHROMIUM} missing: `make test` installs Debian's chromium package when run as root")


@pytest.fixture(scope="module")
def page(report):
    with Browser(width_px=1280, height_px=900) as b:
        b.goto(report.resolve().as_uri())
        assert b.eval("document.documentElement.getAttribute('data-report-ready')") == "1"
        yield b


def test_loads_cleanly_offline(page, report):
    assert page.errors() == []
    urls = page.requested_urls()
    assert urls and all(u.startswith(("file://", "data:")) for u in urls), [u for u in urls
                                                                          if not u.startswith("file://")]
    broken = page.eval("Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0))"
                       ".map(i => i.getAttribute('src'))")
    assert broken == []
    assert page.eval("document.images.length") > 60  # pictures and plots are really on the page


def test_screenshot(page, tmp_path):
    from PIL import Image

    shot = page.screenshot(tmp_path / "report.png")
    keep = os.environ.get("COBGS_REPORT_SCREENSHOT")
    if keep:
        Path(keep).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, keep)
    with Image.open(shot) as im:
        assert im.width == 1280 and im.height > 3000
        lo, hi = im.convert("L").getextrema()
        assert hi - lo > 200  # not a blank page


def _column(page, table: str, col: int) -> list:
    return page.eval(f"Array.from(document.querySelectorAll('#{table} tbody tr'))"
                     f".map(r => r.cells[{col}].getAttribute('data-sort'))")


def test_table_sort(page):
    heads = page.eval("Array.from(document.querySelectorAll('#t-object thead th')).map(t => t.textContent.trim())")
    col = next(i for i, h in enumerate(heads) if h.startswith("IoU"))
    sel = f"#t-object thead th:nth-child({col + 1}) button"
    page.click(sel)
    asc = _column(page, "t-object", col)
    nums = [float(v) for v in asc if v != ""]
    assert nums == sorted(nums) and len(nums) == 13
    assert asc[-1] == ""  # the failed item has no IoU: last, not first
    assert page.eval(f"document.querySelector('{sel}').parentNode.getAttribute('aria-sort')") == "ascending"
    page.click(sel)
    desc = _column(page, "t-object", col)
    assert [float(v) for v in desc if v != ""] == sorted(nums, reverse=True) and desc[-1] == ""
    assert page.eval(f"document.querySelector('{sel}').parentNode.getAttribute('aria-sort')") == "descending"
    methods = page.eval("Array.from(document.querySelectorAll('#t-object tbody tr'))"
                        ".map(r => r.cells[1].getAttribute('data-sort'))")
    assert methods[0] == "cobgs"  # a perfect IoU sorts first, descending
    # a text column sorts alphabetically
    page.click("#t-object thead th:nth-child(2) button")
    assert _column(page, "t-object", 1) == sorted(_column(page, "t-object", 1))


def test_comparison_toggle_and_slider(page):
    box = ".compare"
    data = json.loads(page.eval(f"document.querySelector('{box} script.cmp-data').textContent"))["methods"]
    ref = page.eval(f"document.querySelector('{box}').getAttribute('data-ref')")
    right = lambda: page.eval(f"document.querySelector('{box} img.cmp-right').getAttribute('src')")  # noqa: E731
    left = lambda: page.eval(f"document.querySelector('{box} img.cmp-left').getAttribute('src')")  # noqa: E731
    assert ref == "cobgs" and left() == data["cobgs"]["overlay"] and right() == data["no_bgtr"]["overlay"]
    page.click(f"{box} button[data-method='nosplit']")
    assert right() == data["nosplit"]["overlay"] and left() == data["cobgs"]["overlay"]
    assert page.eval(f"document.querySelector(\"{box} button[data-method='nosplit']\").getAttribute('aria-pressed')"
                     ) == "true"
    assert page.eval(f"document.querySelector(\"{box} button[data-method='no_bgtr']\").getAttribute('aria-pressed')"
                     ) == "false"
    assert page.eval(f"document.querySelector('{box} .cmp-tag.right').textContent") == "nosplit"
    page.click(f"{box} button[data-kind='crop']")
    assert left() == data["cobgs"]["crop"] and right() == data["nosplit"]["crop"]
    # the image the toggle switched to loads (waits for it: the machine may be busy)
    loaded = page.eval(f"""new Promise(done => {{
        const img = document.querySelector('{box} img.cmp-right');
        if (img.complete) return done(img.naturalWidth);
        img.addEventListener('load', () => done(img.naturalWidth));
        img.addEventListener('error', () => done(0));
        setTimeout(() => done(-1), 10000);
    }})""")
    assert loaded > 0
    page.eval(f"(function(){{var r=document.querySelector('{box} input.cmp-range'); r.value=20;"
              f"r.dispatchEvent(new Event('input'));}})()")
    assert page.eval(f"document.querySelector('{box} img.cmp-right').style.clipPath") == "inset(0px 0px 0px 20%)"
    assert page.errors() == []
