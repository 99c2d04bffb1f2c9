"""Render the Rerun review of a recording in headless Chromium and save it as a PNG (the README's screenshots).

Run from the repository root::

    pip install websocket-client          # a requirement of this docs script only, not of starenv
    python docs/review/render_review.py                 # records paper_004 (12 steps, seed 0), writes
                                                        # docs/review/review_paper_004.png
    python docs/review/render_review.py --drops         # also stress_drops -> docs/review/review_stress_drops.png
    python docs/review/render_review.py --bodies        # also moon_in_field -> docs/review/review_moon_in_field.png
    python docs/review/render_review.py FILE.rrd --out shot.png     # an existing review (.rrd) or MCAP (.mcap)

It needs the ``rerun`` binary (the ``rerun-sdk`` package's ``rerun_cli``, or ``rerun`` on PATH) and Chromium
(``chromium`` or ``chromium-browser`` on PATH, e.g. Debian's package).  Without a GPU Chromium renders WebGL with
SwiftShader (``--use-gl=angle --use-angle=swiftshader --enable-unsafe-swiftshader``), which is slow: the page gets
``--wait`` seconds of real time to load the viewer and stream the recording before the screenshot.  The viewer is
served on 127.0.0.1 only; the server and the browser are stopped (their process groups killed) however the script
ends.  Screenshots are 1600x1000 px, downscaled when the PNG would exceed ``--max-kb``.  Not run in CI.
"""

import argparse
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT = 1600, 1000
# the CLI through the interpreter running this script (the package has no __main__)
STARENV = [sys.executable, "-c", "import sys; from starenv.cli import main; sys.exit(main())"]
CHROMIUM_GL_FLAGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def rerun_binary() -> str:
    """The rerun CLI: the binary shipped in ``rerun_cli`` (rerun-sdk), else ``rerun`` on PATH."""
    try:
        import rerun_cli

        candidate = Path(rerun_cli.__file__).resolve().parent / "rerun"
        if candidate.is_file():
            return str(candidate)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if found is None:
        sys.exit("rerun not found: pip install rerun-sdk")
    return found


def chromium_binary() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    sys.exit("chromium not found on PATH (e.g. apt-get install chromium)")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def stop(proc: subprocess.Popen | None) -> None:
    """Kill a process started with its own session, with all its children."""
    if proc is None or proc.poll() is not None:
        return
    for sig, grace_s in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(grace_s)
            return
        except subprocess.TimeoutExpired:
            continue


def record(scenario: str, steps: int, seed: int, rrd: Path) -> None:
    subprocess.run(STARENV + ["run", scenario, "--steps", str(steps), "--seed", str(seed),
                    "--rrd", str(rrd), "--quiet"], check=True)


def review_of(source: Path, workdir: Path) -> Path:
    """The .rrd to serve: the file itself, or the review ``starenv view`` writes for an MCAP."""
    if source.suffix == ".rrd":
        return source
    rrd = workdir / (source.stem + ".rrd")
    subprocess.run(STARENV + ["view", str(source), "--rrd", str(rrd)], check=True)
    return rrd


def devtools_screenshot(ws_url: str, page_url: str, wait_s: float) -> bytes:
    """Open ``page_url`` in the tab behind ``ws_url``, wait ``wait_s`` of real time, return a PNG of the viewport."""
    import websocket  # websocket-client: needed by this docs script only

    ws = websocket.create_connection(ws_url, timeout=120, suppress_origin=True)
    try:
        next_id = 0

        def call(method: str, **params):
            nonlocal next_id
            next_id += 1
            ws.send(json.dumps({"id": next_id, "method": method, "params": params}))
            while True:
                msg = json.loads(ws.recv())
                if msg.get("id") == next_id:
                    if "error" in msg:
                        raise RuntimeError(f"{method}: {msg['error']}")
                    return msg["result"]

        call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1, mobile=False)
        call("Page.enable")
        call("Page.navigate", url=page_url)
        time.sleep(wait_s)
        return base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
    finally:
        ws.close()


def screenshot(rrd: Path, wait_s: float, workdir: Path) -> bytes:
    """Serve ``rrd`` with Rerun's web viewer on 127.0.0.1 and screenshot it in headless Chromium."""
    web_port, grpc_port, debug_port = free_port(), free_port(), free_port()
    server = browser = None
    try:
        server = subprocess.Popen(
            [rerun_binary(), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web_port),
             "--port", str(grpc_port), str(rrd)],
            env={**os.environ, "CI": "1"},  # Rerun skips its usage analytics while CI is set
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        browser = subprocess.Popen(
            [chromium_binary(), "--headless", "--no-sandbox", *CHROMIUM_GL_FLAGS, f"--window-size={WIDTH},{HEIGHT}",
             f"--remote-debugging-port={debug_port}", "--remote-debugging-address=127.0.0.1",
             f"--user-data-dir={workdir / f'chromium-{debug_port}'}", "--no-first-run", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 30
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{debug_port}/json") as reply:
                    tabs = json.load(reply)
                page = next(tab for tab in tabs if tab["type"] == "page")
                break
            except (OSError, StopIteration):
                if time.monotonic() > deadline or browser.poll() is not None or server.poll() is not None:
                    raise RuntimeError("chromium's DevTools or the rerun server did not come up") from None
                time.sleep(0.2)
        proxy = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
        return devtools_screenshot(page["webSocketDebuggerUrl"], f"http://127.0.0.1:{web_port}/?url={proxy}", wait_s)
    finally:
        stop(browser)
        stop(server)


def write_png(png: bytes, out: Path, max_kb: float) -> None:
    """Write ``png`` to ``out``, downscaled (area interpolation) until the file is under ``max_kb``."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if image is None or image.std() == 0:
        raise RuntimeError("the screenshot is empty or a single colour: the viewer did not render")
    scale = 1.0
    while True:
        scaled = image if scale == 1.0 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        ok, encoded = cv2.imencode(".png", scaled, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not ok:
            raise RuntimeError("PNG encoding failed")
        if len(encoded) <= max_kb * 1024 or scale < 0.3:
            break
        scale *= 0.85
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(encoded.tobytes())
    print(f"wrote {out} ({scaled.shape[1]}x{scaled.shape[0]} px, {len(encoded) // 1024} KB)", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", nargs="?", type=Path, help="a review .rrd or an MCAP to review (default: record one)")
    parser.add_argument("--scenario", default="paper_004", help="scenario to record when no source is given")
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="PNG to write (default: docs/review/review_SCENARIO.png)")
    parser.add_argument("--drops", action="store_true", help="also render stress_drops (a run with dropped frames)")
    parser.add_argument("--bodies", action="store_true", help="also render moon_in_field (the Moon on the frame, the "
                                                               "Sun, Moon and planets in the 3-D view)")
    parser.add_argument("--wait", type=float, default=90.0, help="real seconds the page gets before the screenshot")
    parser.add_argument("--max-kb", type=float, default=700.0, help="largest PNG size, KB")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="starenv-review-") as tmp:
        workdir = Path(tmp)
        jobs = []
        if args.source is not None:
            jobs.append((review_of(args.source, workdir), args.out or HERE / f"review_{args.source.stem}.png"))
        else:
            rrd = workdir / f"{args.scenario}.rrd"
            record(args.scenario, args.steps, args.seed, rrd)
            jobs.append((rrd, args.out or HERE / f"review_{args.scenario}.png"))
        if args.drops:
            rrd = workdir / "stress_drops.rrd"
            record("stress_drops", args.steps, args.seed, rrd)
            jobs.append((rrd, HERE / "review_stress_drops.png"))
        if args.bodies:
            rrd = workdir / "moon_in_field.rrd"
            record("moon_in_field", args.steps, args.seed, rrd)
            jobs.append((rrd, HERE / "review_moon_in_field.png"))
        for rrd, out in jobs:
            write_png(screenshot(rrd, args.wait, workdir), out, args.max_kb)


if __name__ == "__main__":
    main()
