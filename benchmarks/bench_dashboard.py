"""``cobel serve`` with 1,000 run folders: how long the folder list takes to load.

Run on demand (not a test)::

    python benchmarks/bench_dashboard.py [--runs 1000] [--browser]

Makes one real tiny run (``tmaze_extinction``, 2 runs x 200 trials), copies its folder
``--runs`` times into a temporary results folder, then measures

1. ``scan``: :func:`cobelrun.web.data.scan` (every manifest validated), cold;
2. ``first_get``: ``cobel serve`` started, the first ``GET /`` (the page with every row);
3. ``second_get``: a second ``GET /`` (rows re-read only for folders that changed);
4. with ``--browser``: headless Chromium until the page says "N folders" (load to rows shown).

Prints one JSON line and writes ``benchmarks/results/bench_dashboard.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--browser", action="store_true", help="also time headless Chromium")
    args = ap.parse_args()

    import cobelrun
    from cobelrun.web import data

    with tempfile.TemporaryDirectory(prefix="cobel-bench-dash-") as tmp:
        root = Path(tmp) / "results"
        one = cobelrun.run("tmaze_extinction", ["task.runs=2"], out=Path(tmp) / "one")
        for i in range(args.runs):
            shutil.copytree(one.path, root / "tmaze_extinction" / f"d{i // 100:02d}" / f"r{i:04d}")
        size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())

        t = time.perf_counter()
        rows = data.scan(root)
        scan_s = time.perf_counter() - t
        assert len(rows) == args.runs, len(rows)

        port = _free_port()
        env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
        env["PYTHONPATH"] = str(REPO)
        proc = subprocess.Popen(
            [sys.executable, "-c", "from cobelrun.cli import main; main()", "serve", str(root),
             "--port", str(port)],
            env=env,
        )  # fmt: skip
        try:
            url = f"http://127.0.0.1:{port}/"
            t0 = time.perf_counter()
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                    break
                except OSError:
                    time.sleep(0.1)
            start_s = time.perf_counter() - t0
            t = time.perf_counter()
            html = urllib.request.urlopen(url, timeout=120).read().decode()
            first_s = time.perf_counter() - t
            assert f"{args.runs} folders" in html
            t = time.perf_counter()
            urllib.request.urlopen(url, timeout=120).read()
            second_s = time.perf_counter() - t
            browser_s = None
            if args.browser:
                browser_s = _browser(url, f"{args.runs} folders")
        finally:
            proc.terminate()
            proc.wait(10)
    result = {
        "runs": args.runs,
        "results_bytes": size,
        "scan_s": round(scan_s, 3),
        "server_start_s": round(start_s, 3),
        "first_get_s": round(first_s, 3),
        "second_get_s": round(second_s, 3),
        "html_bytes": len(html),
        "browser_rows_shown_s": None if browser_s is None else round(browser_s, 3),
        "cpus": os.cpu_count(),
    }
    print(json.dumps(result))
    out = REPO / "benchmarks" / "results" / "bench_dashboard.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")


def _browser(url: str, text: str) -> float:
    from selenium import webdriver
    from selenium.webdriver.common.by import By

    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(
        options=opts, service=webdriver.ChromeService(executable_path="/usr/bin/chromedriver")
    )
    try:
        t = time.perf_counter()
        driver.get(url)
        while True:
            els = driver.find_elements(By.CSS_SELECTOR, ".cobel-count")
            if els and els[0].text == text:
                return time.perf_counter() - t
            time.sleep(0.05)
    finally:
        driver.quit()


if __name__ == "__main__":
    main()
