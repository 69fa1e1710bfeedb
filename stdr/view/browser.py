"""A headless Chromium that opens a page and takes a screenshot when told (the DevTools protocol
over a websocket): `stdr-view --screenshot` and the browser test use it."""
from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Callable, Optional

CHROMIUMS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> Optional[str]:
    for name in CHROMIUMS:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(url: str, out: str | Path, ready: Callable[[], bool], width: int = 1200, height: int = 800,
               timeout: float = 120.0, settle: float = 1.5) -> Path:
    """Open `url` in headless Chromium, wait until `ready()` is true (polled), `settle` seconds
    more for the page to draw, and save a PNG screenshot to `out`."""
    exe = find_chromium()
    if exe is None:
        raise RuntimeError("no Chromium found: apt-get install -y chromium")
    from websockets.sync.client import connect
    out = Path(out)
    # ignore_cleanup_errors: a helper that outlived stop_process_group may still write to the
    # profile; the screenshot is saved by then and must not fail on the leftover files
    with tempfile.TemporaryDirectory(prefix="stdr-chromium-", ignore_cleanup_errors=True) as prof:
        proc = subprocess.Popen([exe, "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                                 "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                                 "--no-first-run", "--remote-debugging-port=0", f"--user-data-dir={prof}",
                                 f"--window-size={width},{height}", url],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "HOME": prof},
                                start_new_session=True)  # its own process group: its helpers are stopped with it
        try:
            t0 = time.time()
            port_file = Path(prof) / "DevToolsActivePort"
            while not port_file.is_file() or not port_file.read_text().strip():
                if proc.poll() is not None:
                    raise RuntimeError(f"Chromium exited with {proc.returncode} before opening its DevTools port")
                if time.time() - t0 > timeout:
                    raise TimeoutError("Chromium did not open its DevTools port")
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            pages = []
            while not pages:
                targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
                pages = [t for t in targets if t.get("type") == "page" and t.get("url", "").startswith(url)]
                if time.time() - t0 > timeout:
                    raise TimeoutError(f"Chromium did not open {url}")
                time.sleep(0.1)
            while not ready():
                if time.time() - t0 > timeout:
                    raise TimeoutError(f"the page at {url} was not ready within {timeout:.0f} s")
                time.sleep(0.2)
            time.sleep(settle)
            with connect(pages[0]["webSocketDebuggerUrl"], max_size=2 ** 26, open_timeout=30) as ws:
                ws.send(json.dumps({"id": 1, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
                while True:
                    msg = json.loads(ws.recv(timeout=60))
                    if msg.get("id") == 1:
                        break
            if "result" not in msg:
                raise RuntimeError(f"Chromium could not take the screenshot: {msg.get('error')}")
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(base64.b64decode(msg["result"]["data"]))
            return out
        finally:
            stop_process_group(proc)


def stop_process_group(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """Stop a process started with start_new_session=True and every process of its group.
    Chromium forks helpers (renderer, GPU, crashpad) that outlive a terminated main process and
    keep writing to the profile folder, which then could not be removed. SIGTERM to the group,
    then SIGKILL to whatever is left after `timeout` seconds; waits for the group to be gone
    (bounded: zombies of an init that does not reap would keep it alive)."""
    import signal
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        deadline = time.time() + timeout
        while time.time() < deadline:
            proc.poll()  # reap the main process
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pass
