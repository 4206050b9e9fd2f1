"""Shared pieces of the browser tests (``cobel serve``, ``cobel edit``): a free port, a web
command started in its own process until it listens, and Debian's headless Chromium driven by
selenium (skipped with a one-line reason where either is missing)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def web_command(args: list[str], port: int, cwd: Path | None = None,
                stop_timeout: float = 15.0) -> Iterator[str]:  # fmt: skip
    """Start ``cobel ARGS`` (a web app listening on ``port``) from this checkout, yield its URL
    once it listens (a test fails if it exits or does not listen within 60 s), stop it after."""
    pytest.importorskip("nicegui", reason=f"cobel {args[0]} needs the web extra (NiceGUI)")
    # NiceGUI takes a process with PYTEST_CURRENT_TEST for its own test harness
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    env.update(PYTHONPATH=str(REPO), COBEL_DEBUG="1")
    cmd = [sys.executable, "-c", "from cobelrun.cli import main; main()", *args]
    proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)  # fmt: skip
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
        except OSError:
            if proc.poll() is not None:
                out = proc.stdout.read().decode() if proc.stdout else ""
                pytest.fail(f"cobel {args[0]} exited: {out}")
            time.sleep(0.2)
    else:
        proc.kill()
        pytest.fail(f"cobel {args[0]} did not listen within 60 s")
    yield f"http://127.0.0.1:{port}"
    proc.terminate()
    try:
        proc.wait(stop_timeout)
    except subprocess.TimeoutExpired:
        proc.kill()


def headless_chromium(width: int) -> Iterator[object]:
    """A selenium driver of Debian's headless Chromium, ``width`` x 1000 pixels; quit after."""
    if not (CHROMIUM.is_file() and CHROMEDRIVER.is_file()):
        pytest.skip(f"needs Debian's chromium and chromium-driver ({CHROMIUM}, {CHROMEDRIVER}); "
                    "`apt-get install chromium chromium-driver` (.ci/run does)")  # fmt: skip
    webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium (dev extra)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                f"--window-size={width},1000"):  # fmt: skip
        opts.add_argument(arg)
    service = webdriver.ChromeService(executable_path=str(CHROMEDRIVER))
    driver = webdriver.Chrome(options=opts, service=service)
    yield driver
    driver.quit()
