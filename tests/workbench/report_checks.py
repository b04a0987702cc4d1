"""Checks shared by the tests of the HTML report (test_run.py: a study's report; test_report.py: the pieces)."""

from __future__ import annotations

import base64
import io
import shutil
from html.parser import HTMLParser
from pathlib import Path

MAX_BYTES = 5 * 2**20  # issue J: a test-size report stays under ~5 MB


class _Parse(HTMLParser):
    """Tables (rows of cell texts), images (src), toggles, section headings and scripts of a page."""

    def __init__(self):
        super().__init__()
        self.tables, self.images, self.toggles, self.headings, self.external = [], [], 0, [], []
        self._cell = None
        self._h2 = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = ""
        elif tag == "img":
            self.images.append(a.get("src", ""))
        elif tag == "div" and a.get("class") == "toggle":
            self.toggles += 1
        elif tag == "h2":
            self._h2 = True
            self.headings.append("")
        for k in ("src", "href"):
            v = a.get(k)
            if v and not v.startswith(("data:", "#")):
                self.external.append(v)

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append(self._cell.strip())
            self._cell = None
        elif tag == "h2":
            self._h2 = False

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data
        if self._h2:
            self.headings[-1] += data


def parse(path: Path) -> _Parse:
    p = _Parse()
    p.feed(path.read_text(encoding="utf-8"))
    return p


def decode(src: str):
    from PIL import Image

    assert src.startswith("data:image/"), src[:40]
    data = base64.b64decode(src.split(",", 1)[1], validate=True)
    img = Image.open(io.BytesIO(data))
    img.load()  # decodes every pixel (verify() checks only the structure)
    return img


def chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None
