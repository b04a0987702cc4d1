"""A self-contained HTML page: inline CSS, a few lines of script, images as data URIs, nothing fetched.

:class:`Page` collects sections; ``Page.html()`` returns the document.  A
*toggle* is two pictures in one frame (the registered template and its
target, NiPreps-style): a button swaps them, and "flicker" alternates them
twice a second, so that a misregistration shows as motion.
"""

from __future__ import annotations

import base64
import html
import math

__all__ = ["Page", "esc", "table_html"]

CSS = """
body{font:14px/1.45 system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:0;color:#1d1d22;
background:#fafafa}
header{background:#2b2540;color:#fff;padding:18px 28px}header h1{margin:0 0 4px;font-size:22px}
header p{margin:0;opacity:.85}nav{padding:8px 28px;background:#eee9f5;font-size:13px}
nav a{margin-right:14px;color:#40306a}
main{padding:8px 28px 40px;max-width:1280px}section{margin:26px 0}h2{border-bottom:2px solid #8a4fbf;padding-bottom:3px}
h3{margin:18px 0 6px}table{border-collapse:collapse;margin:8px 0;font-size:13px;background:#fff}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#f0ecf6}
td:first-child,th:first-child{text-align:left}
tr.paper td{color:#5a5a70;font-style:italic}tr.peer td{color:#33506a}
.figs{display:flex;flex-wrap:wrap;gap:12px;align-items:flex-start}
figure{margin:0;background:#fff;padding:6px;border:1px solid #ddd}
figcaption{font-size:12px;color:#444;max-width:440px}.toggle{position:relative;display:inline-block}
.toggle img.b{position:absolute;left:0;top:0;visibility:hidden}.toggle.show-b img.b{visibility:visible}
.toggle.flicker img.b{animation:flick 1s steps(1) infinite}@keyframes flick{50%{visibility:visible}}
button{font-size:12px;margin:2px 4px 2px 0}.note{color:#555;font-size:13px}.bad{color:#b00020;font-weight:600}
dl{font-size:13px}dt{font-weight:600}dd{margin:0 0 6px 18px}code{background:#f0f0f0;padding:0 3px}
footer{font-size:12px;color:#444;border-top:1px solid #ccc;margin-top:30px;padding-top:8px}
"""

SCRIPT = """
function tg(id){var e=document.getElementById(id);e.classList.remove('flicker');e.classList.toggle('show-b');}
function fl(id){var e=document.getElementById(id);e.classList.remove('show-b');e.classList.toggle('flicker');}
"""


def esc(text) -> str:
    return html.escape(str(text), quote=True)


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _mime(data: bytes) -> str:
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    if data[:3] == b"\xff\xd8\xff":
        return "image/jpeg"
    if data[:6] in (b"GIF87a", b"GIF89a"):
        return "image/gif"
    raise ValueError("an embedded picture must be PNG, JPEG or GIF")


def _num(v, decimals: int) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, bool) or isinstance(v, str):
        return esc(v)
    if isinstance(v, int) or decimals == 0:
        return str(int(round(v)))
    return f"{v:.{decimals}f}"


def table_html(headings, rows, *, decimals=None, classes=None, caption: str = "") -> str:
    """An HTML table; ``rows`` are lists of cells (numbers formatted to ``decimals[c]`` places)."""
    decimals = decimals or [2] * len(headings)
    out = ["<table>"]
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    out.append("<tr>" + "".join(f"<th>{esc(h)}</th>" for h in headings) + "</tr>")
    for r, row in enumerate(rows):
        cls = f' class="{esc(classes[r])}"' if classes and classes[r] else ""
        out.append(f"<tr{cls}>" + "".join(f"<td>{_num(v, d)}</td>" for v, d in zip(row, decimals)) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


class Page:
    """The report page (module docstring)."""

    def __init__(self, title: str, subtitle: str = ""):
        self.title = title
        self.subtitle = subtitle
        self.sections: list[tuple[str, str, list[str]]] = []  # (anchor, heading, parts)
        self.footer: list[str] = []
        self._ids = 0

    def section(self, heading: str) -> list[str]:
        parts: list[str] = []
        self.sections.append((f"s{len(self.sections)}", heading, parts))
        return parts

    def image(self, data: bytes, caption: str = "", *, alt: str = "") -> str:
        return (
            f'<figure><img src="{data_uri(data, _mime(data))}" alt="{esc(alt or caption)}" loading="lazy">'
            f"<figcaption>{esc(caption)}</figcaption></figure>"
        )

    def video(self, data: bytes, caption: str = "") -> str:
        """An MP4 (ISO base media: ``ftyp`` box at byte 4) embedded whole, looping without sound."""
        if data[4:8] != b"ftyp":
            raise ValueError("an embedded video must be MP4")
        return (
            f'<figure><video src="{data_uri(data, "video/mp4")}" controls loop muted playsinline '
            f'preload="metadata"></video><figcaption>{esc(caption)}</figcaption></figure>'
        )

    def toggle(self, a: bytes, b: bytes, caption: str, *, names=("registered template", "target scan")) -> str:
        """Two pictures of one size in one frame: ``a`` shown, ``b`` on the button or flickering."""
        self._ids += 1
        i = f"t{self._ids}"
        return (
            f'<figure><div class="toggle" id="{i}"><img class="a" src="{data_uri(a, _mime(a))}" '
            f'alt="{esc(names[0])}"><img class="b" src="{data_uri(b, _mime(b))}" alt="{esc(names[1])}"></div>'
            f"<br><button onclick=\"tg('{i}')\">{esc(names[0])} / {esc(names[1])}</button>"
            f"<button onclick=\"fl('{i}')\">flicker</button><figcaption>{esc(caption)}</figcaption></figure>"
        )

    def html(self) -> str:
        nav = "".join(f'<a href="#{a}">{esc(h)}</a>' for a, h, _ in self.sections)
        body = "".join(f'<section id="{a}"><h2>{esc(h)}</h2>{"".join(p)}</section>' for a, h, p in self.sections)
        foot = "".join(self.footer)
        return (
            f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{esc(self.title)}</title>'
            f'<meta name="viewport" content="width=device-width,initial-scale=1"><style>{CSS}</style>'
            f"<script>{SCRIPT}</script></head><body><header><h1>{esc(self.title)}</h1>"
            f"<p>{esc(self.subtitle)}</p></header><nav>{nav}</nav><main>{body}<footer>{foot}</footer></main>"
            "</body></html>\n"
        )
