"""``workbench view``: the time from a slider move to the updated image in the browser (issue O).

Starts ``workbench view STUDY --no-browser --port 0``, opens the page in headless Chromium (Selenium) and
moves the first joint's first slider ``--moves`` times as a drag does: the page's state is set from the
browser (``trame.state.set``, what the slider's ``v-model`` does).  A MutationObserver on the view's image
records when each new image arrives (``performance.now()``, the browser's clock, as the move).  Per move:

* **coarse**: the first image after the move (the maps on every 2nd voxel);
* **exact**: the image the server sends once the slider has stopped for ``SETTLE_S`` (the maps on every
  voxel), counted from the move — so it includes that wait.

Prints the median and the largest of each over the moves, and the server's own deform time (its status
line).  The default study is the demo's (``make demo``: a 128×128×59 knee at 2.5 mm with an EVD model).

Usage::

    .venv/bin/python benchmarks/bench_viewer.py                      # demo-study, 20 moves
    .venv/bin/python benchmarks/bench_viewer.py STUDY --moves 20 --size 800x600
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

OBSERVE = """
const img = document.querySelector('#view img');
window.__frames = [];
new MutationObserver(() => window.__frames.push(performance.now()))
  .observe(img, {attributes: true, attributeFilter: ['src']});
"""


def _browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    o = Options()
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1280,900"):
        o.add_argument(a)
    d = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=o)
    d.implicitly_wait(60)
    return d


def _quiet_for(d, seconds: float, limit: float = 30.0) -> None:
    """Wait until no new image has arrived for ``seconds``."""
    t0 = time.monotonic()
    n = d.execute_script("return window.__frames.length")
    last = time.monotonic()
    while time.monotonic() - t0 < limit:
        time.sleep(0.1)
        m = d.execute_script("return window.__frames.length")
        if m != n:
            n, last = m, time.monotonic()
        elif time.monotonic() - last >= seconds:
            return


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("study", nargs="?", default="demo-study", type=Path)
    ap.add_argument("--moves", type=int, default=20)
    ap.add_argument("--size", default="800x600")
    args = ap.parse_args(argv)
    if not (args.study / "study.json").is_file():
        print(f"{args.study}: no study there; `make demo` builds demo-study", file=sys.stderr)
        return 2
    from workbench.study import read_study
    from workbench.viz.viewer import Dof
    from workbench.viz.viewer_app import SETTLE_S

    sk = read_study(args.study).skeleton()
    j = sk.joints[0]
    lo, hi = j.limits[0] if j.limits else (-90.0, 90.0)
    key = Dof(j.name, 0, lo, hi).key
    p = subprocess.Popen(
        [sys.executable, "-m", "workbench", "view", str(args.study), "--no-browser", "--port", "0"]
        + ["--size", args.size, "--out", "/tmp/bench-viewer-out"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    url = None
    for line in p.stdout:
        if "serving" in line:
            url = line.split(" at ", 1)[1].split()[0]
            break
    if url is None:
        print("workbench view did not start", file=sys.stderr)
        return 1
    threading.Thread(target=lambda: [None for _ in p.stdout], daemon=True).start()
    d = _browser()
    try:
        d.get(url)
        d.find_element("css selector", "#view img")
        time.sleep(2.0)
        d.execute_script(OBSERVE)
        _quiet_for(d, 1.0)
        coarse, exact, server = [], [], []
        values = np.linspace(lo + 0.1 * (hi - lo), lo + 0.6 * (hi - lo), args.moves)
        for i, v in enumerate(values):
            v = float(np.round(v, 1)) + (0.5 if i % 2 else 0.0)
            t0 = d.execute_script(f"const t = performance.now(); window.trame.state.set({key!r}, {v}); return t;")
            _quiet_for(d, SETTLE_S + 1.0)
            frames = [f for f in d.execute_script("return window.__frames") if f > t0]
            status = d.find_element("id", "status").text
            m = re.search(r"deform ([0-9.]+) s", status)
            if len(frames) < 2 or "exact" not in status:
                print(f"move {i + 1}: {len(frames)} image(s), status {status!r}: skipped")
                continue
            coarse.append((frames[0] - t0) / 1000.0)
            exact.append((frames[-1] - t0) / 1000.0)
            server.append(float(m.group(1)) if m else float("nan"))
        # a drag: 10 changes 50 ms apart; the last one's exact image, counted from that last change
        drag = []
        sweep = [float(x) for x in np.linspace(values[0], values[-1], 10)]
        for rep in range(3):
            t_last = d.execute_script(
                f"const vs = {sweep[:: 1 if rep % 2 == 0 else -1]};"
                f"return await new Promise(done => {{ let i = 0; const step = () => {{"
                f" window.trame.state.set({key!r}, vs[i] + 0.25 * {rep}); const t = performance.now();"
                f" if (++i < vs.length) setTimeout(step, 50); else done(t); }}; step(); }});"
            )
            _quiet_for(d, SETTLE_S + 1.0)
            frames = [f for f in d.execute_script("return window.__frames") if f > t_last]
            if frames:
                drag.append((frames[-1] - t_last) / 1000.0)
        n = len(coarse)
        print(f"workbench view, {args.study} ({args.size}), {n} moves of {j.name}[0] ({lo:g}..{hi:g}°):")
        print(f"  coarse image after a move: median {np.median(coarse):.2f} s, largest {np.max(coarse):.2f} s")
        print(
            f"  exact image after a move:  median {np.median(exact):.2f} s, largest {np.max(exact):.2f} s "
            f"(of which {SETTLE_S:g} s waiting for the slider to stop)"
        )
        print(f"  the server's exact deform (status line): median {np.nanmedian(server):.2f} s")
        if drag:
            print(
                f"  a drag (10 changes 50 ms apart), its last change to the exact image: "
                f"median {np.median(drag):.2f} s, largest {np.max(drag):.2f} s over {len(drag)} drags"
            )
    finally:
        d.quit()
        p.terminate()
        p.wait(timeout=30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
