"""Screenshots of the live view in a real Foxglove Studio web app (docs/img/live-*.png).

Foxglove's desktop app does not run on a headless machine, but the last open-source
Foxglove Studio (MPL-2.0) is on npm: ``@foxglove/studio-base@1.48.0`` ships, besides its
sources, ``assets/index.js``: the whole app as one webpack bundle (UMD; React 17 and ReactDOM
17 are its only externals) with its panels, workers and WebAssembly next to it. This script

1. installs it and React 17 with npm into a throwaway folder (``/tmp/cobel-studio`` by
   default; nothing is vendored in this repository),
2. writes there an ``index.html`` that loads React, ReactDOM and the bundle and mounts the
   bundle's ``App`` with its ``FoxgloveWebSocketDataSourceFactory`` and an in-memory layout
   store holding cobel's shipped layout (``cobelrun/io/layouts/cobel-live.lichtblick.json``:
   the Foxglove Studio 1.x / Lichtblick format),
3. serves that folder on ``127.0.0.1`` (Python's ``http.server``),
4. starts ``cobel run TASK --port P task.record.live_wait=...`` (a real run, its live view on
   ``ws://127.0.0.1:P``),
5. opens ``http://127.0.0.1:H/?ds=foxglove-websocket&ds.url=ws://127.0.0.1:P&layoutId=...``
   in Debian's headless ``chromium`` (selenium + ``chromedriver``): the app connects to the
   run through the URL, as a deep link, and selects the layout,
6. takes screenshots while the run goes.

Usage (from the repository root)::

    python benchmarks/shoot_live_view.py                       # docs/img/live-studio*.png
    python benchmarks/shoot_live_view.py --task dyna_maze --out /tmp/shots

Needs ``npm`` (registry access), ``/usr/bin/chromium``, ``/usr/bin/chromedriver``, and the
``selenium`` (dev extra) and ``websockets`` packages (the relay: :func:`relay`). It is a docs
tool, not a test: nothing here is asserted.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from cobelrun.io.live import lichtblick_layout  # noqa: E402

#: the last open-source Foxglove Studio on npm, and the React it was built against
PACKAGES = ("@foxglove/studio-base@1.48.0", "react@17.0.2", "react-dom@17.0.2")
BUNDLE = "node_modules/@foxglove/studio-base/assets/index.js"
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
LAYOUT_ID = "cobel-live"

INDEX_HTML = """<!doctype html>
<html>
<head>
<meta charset="utf-8">
<title>cobel live view (Foxglove Studio 1.48)</title>
<style>html, body, #root { height: 100%; margin: 0; }</style>
</head>
<body>
<div id="root"></div>
<script src="node_modules/react/umd/react.production.min.js"></script>
<script src="node_modules/react-dom/umd/react-dom.production.min.js"></script>
<script>window.react = window.React; window["react-dom"] = window.ReactDOM;</script>
<script src="BUNDLE"></script>
<script src="cobel-live.js"></script>
</body>
</html>
"""

# The glue: what Foxglove Studio's own web entry point does, minus the accounts, extensions
# marketplace and IndexedDB (settings and layouts live in memory; the layout is cobel's).
MOUNT_JS = """
(async function () {
  const layoutData = LAYOUT_JSON;
  const now = new Date().toISOString();
  const layouts = new Map([["LAYOUT_ID", {
    id: "LAYOUT_ID", name: "cobel live", permission: "CREATOR_WRITE",
    baseline: { data: layoutData, savedAt: now }, working: undefined, syncInfo: undefined,
  }]]);
  const layoutStorage = {
    async list(ns) { return ns === "local" ? [...layouts.values()] : []; },
    async get(ns, id) { return ns === "local" ? layouts.get(id) : undefined; },
    async put(ns, layout) { layouts.set(layout.id, layout); return layout; },
    async delete(ns, id) { layouts.delete(id); },
    async importLayouts() {},
    async migrateUnnamespacedLayouts() {},
  };
  const settings = new Map([["colorScheme", "light"], ["telemetry.telemetryEnabled", false],
                            ["telemetry.crashReportingEnabled", false],
                            ["hideSignInPrompt", true], ["ui.open-dialog-startup", false],
                            ["enableNewImagePanel", true]]);
  const listeners = new Map();
  const appConfiguration = {
    get(key) { return settings.get(key); },
    async set(key, value) {
      settings.set(key, value);
      for (const cb of listeners.get(key) ?? []) cb(value);
    },
    addChangeListener(key, cb) {
      if (!listeners.has(key)) listeners.set(key, new Set());
      listeners.get(key).add(cb);
    },
    removeChangeListener(key, cb) { listeners.get(key)?.delete(cb); },
  };
  await initI18n();
  ReactDOM.render(
    React.createElement(App, {
      deepLinks: [window.location.href],
      appConfiguration,
      dataSources: [new FoxgloveWebSocketDataSourceFactory()],
      layoutStorage,
      extensionLoaders: [],
      enableGlobalCss: true,
      enableLaunchPreferenceScreen: false,
    }),
    document.getElementById("root"),
  );
})();
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def install(folder: Path) -> None:
    """npm-install Foxglove Studio's bundle and React 17 into ``folder`` (once)."""
    if (folder / BUNDLE).is_file() and (folder / "node_modules/react-dom/umd").is_dir():
        return
    npm = shutil.which("npm")
    if npm is None:
        sys.exit("shoot_live_view: needs npm (apt-get install npm)")
    folder.mkdir(parents=True, exist_ok=True)
    print(f"npm install {' '.join(PACKAGES)} into {folder} ...", flush=True)
    subprocess.run([npm, "install", "--no-audit", "--no-fund", "--ignore-scripts",
                    "--prefix", str(folder), *PACKAGES], check=True)  # fmt: skip


def write_page(folder: Path, center: tuple[float, float] | None = None) -> None:
    """The app's page and glue, with cobel's shipped layout in it (its 3D camera looking down
    on ``center`` from above at a slant, when given: the shipped layout keeps Studio's default
    view of the frame's origin, which suits no one maze in particular)."""
    (folder / "index.html").write_text(INDEX_HTML.replace("BUNDLE", BUNDLE), encoding="utf-8")
    layout = lichtblick_layout()
    if center is not None:
        layout["configById"]["3D!maze"]["cameraState"] = {
            "distance": 13.0, "perspective": True, "phi": 35.0, "thetaOffset": 0.0,
            "target": [0, 0, 0], "targetOffset": [center[0], center[1], 0],
            "targetOrientation": [0, 0, 0, 1], "fovy": 45.0, "near": 0.5, "far": 5000,
        }  # fmt: skip
    js = MOUNT_JS.replace("LAYOUT_JSON", json.dumps(layout))
    (folder / "cobel-live.js").write_text(js.replace("LAYOUT_ID", LAYOUT_ID), encoding="utf-8")


def serve(folder: Path) -> tuple[http.server.ThreadingHTTPServer, int]:
    """Serve ``folder`` on 127.0.0.1 (a free port) from a thread."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, int(server.server_address[1])


def relay(upstream_port: int) -> tuple[int, Any]:
    """A WebSocket relay on 127.0.0.1 (a free port): Foxglove Studio 1.x (and Lichtblick, and
    every client built on the open-source ``@foxglove/ws-protocol``) asks for the subprotocol
    ``foxglove.websocket.v1``, which foxglove-sdk 0.30's server no longer accepts (it answers
    HTTP 400 to anything but ``foxglove.sdk.v1``). The relay accepts the old name and passes
    every frame, unchanged, to and from the run's server under the new one. Returns the port
    and a function that stops the relay."""
    import asyncio

    from websockets.asyncio.client import connect
    from websockets.asyncio.server import serve as ws_serve

    upstream = f"ws://127.0.0.1:{upstream_port}"
    ready: dict[str, Any] = {}
    started = threading.Event()

    async def pump(a: Any, b: Any) -> None:
        async for frame in a:
            await b.send(frame)

    async def handler(down: Any) -> None:
        try:
            up = await connect(upstream, subprotocols=["foxglove.sdk.v1"], max_size=None,
                               compression=None)  # fmt: skip
        except OSError:  # the run's server is not up (yet, or any more): the app retries
            await down.close()
            return
        async with up:
            tasks = {asyncio.create_task(pump(down, up)), asyncio.create_task(pump(up, down))}
            _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
        await down.close()

    async def main() -> None:
        stop = asyncio.Event()
        ready["stop"] = lambda: loop.call_soon_threadsafe(stop.set)
        async with ws_serve(handler, "127.0.0.1", 0, subprotocols=["foxglove.websocket.v1"],
                            max_size=None, compression=None) as server:  # fmt: skip
            ready["port"] = int(next(iter(server.sockets)).getsockname()[1])
            started.set()
            await stop.wait()

    loop = asyncio.new_event_loop()
    threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True).start()
    started.wait(10)
    return ready["port"], ready["stop"]


def browser(width: int, height: int) -> Any:
    from selenium import webdriver

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    # WebGL (the 3D panel) through SwiftShader: no GPU here
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--ignore-gpu-blocklist", f"--window-size={width},{height}"):  # fmt: skip
        opts.add_argument(arg)
    service = webdriver.ChromeService(executable_path=str(CHROMEDRIVER))
    return webdriver.Chrome(options=opts, service=service)


def _dismiss_hints(driver: Any) -> None:
    """Close the app's first-use hints (the 3D panel's "Open settings" bubble)."""
    from selenium.webdriver.common.by import By

    path = "//*[contains(text(), 'Open settings to configure')]/ancestor::div[1]//button"
    for button in driver.find_elements(By.XPATH, path):
        try:
            button.click()
        except Exception:  # a hint that went away meanwhile
            pass


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=Path("/tmp/cobel-studio"),
                        help="where npm installs the app (a throwaway folder)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    parser.add_argument("--task", default="gridworld")
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--env", default="blodgett")
    parser.add_argument("--trials", type=int, default=10000, help="trials of the first phase")
    parser.add_argument("--overrides", nargs="*",
                        default=["+env.world.goal_reward=1.0", "task.record.flush_seconds=0.25"],
                        help="more cobel run overrides")  # fmt: skip
    parser.add_argument("--shots", type=float, nargs="+", default=[40.0],
                        help="seconds after the page opens at which to take screenshots")  # fmt: skip
    parser.add_argument("--name", default="live-studio")
    parser.add_argument("--center", type=float, nargs=2, default=[3.5, 2.0],
                        help="where the 3D view looks (world units; the Blodgett maze's middle)")  # fmt: skip
    parser.add_argument("--size", default="1600x1000")
    args = parser.parse_args()
    if not (CHROMIUM.is_file() and CHROMEDRIVER.is_file()):
        sys.exit(f"shoot_live_view: needs {CHROMIUM} and {CHROMEDRIVER} "
                 "(apt-get install chromium chromium-driver)")  # fmt: skip
    for module in ("selenium", "websockets"):
        try:
            __import__(module)
        except ImportError:
            sys.exit(f"shoot_live_view: needs the {module} package (pip install {module})")
    width, height = (int(v) for v in args.size.split("x"))
    folder = args.folder.resolve()
    install(folder)
    write_page(folder, tuple(args.center))
    server, http_port = serve(folder)
    ws_port = _free_port()
    results = Path(tempfile.mkdtemp(prefix="results-", dir=folder))
    cobel = Path(sys.executable).with_name("cobel")
    cmd = [str(cobel), "run", f"task={args.task}", "--port", str(ws_port),
           f"env={args.env}", f"task.runs={args.runs}",
           f"task.protocol.phases.0.trials={args.trials}",
           "task.record.live_wait=120", f"hydra.run.dir={results}/run", *args.overrides]  # fmt: skip
    print(" ".join(cmd), flush=True)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    run = subprocess.Popen(cmd, env=env, cwd=folder)
    driver = None
    stop_relay = None
    try:
        time.sleep(5.0)  # the run builds its env and starts its server
        relay_port, stop_relay = relay(ws_port)
        driver = browser(width, height)
        url = (f"http://127.0.0.1:{http_port}/?ds=foxglove-websocket"
               f"&ds.url=ws://127.0.0.1:{relay_port}&layoutId={LAYOUT_ID}")  # fmt: skip
        print(f"opening {url}", flush=True)
        driver.get(url)
        opened = time.monotonic()
        args.out.mkdir(parents=True, exist_ok=True)
        for i, at in enumerate(sorted(args.shots)):
            time.sleep(max(0.0, at - (time.monotonic() - opened)))
            _dismiss_hints(driver)
            suffix = "" if i == 0 else f"-{i + 1}"
            path = args.out / f"{args.name}{suffix}.png"
            driver.save_screenshot(str(path))
            print(f"wrote {path} ({at:g} s; run {'running' if run.poll() is None else 'done'})",
                  flush=True)  # fmt: skip
        logs = driver.get_log("browser")
        errors = [e["message"] for e in logs if e.get("level") == "SEVERE"]
        for line in errors[:10]:
            print(f"browser: {line[:300]}")
    finally:
        if driver is not None:
            driver.quit()
        server.shutdown()
        if stop_relay is not None:
            stop_relay()
        if run.poll() is None:
            run.terminate()
        run.wait(30)


if __name__ == "__main__":
    main()
