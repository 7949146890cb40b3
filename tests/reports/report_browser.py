"""A minimal headless-Chromium driver over the DevTools protocol on a pipe.

Why not selenium/playwright: Chromium speaks the DevTools protocol as NUL-separated JSON on
file descriptors 3 (commands in) and 4 (replies out) with ``--remote-debugging-pipe``, so
the whole client is the stdlib and this file: no chromedriver to match to the browser
version, no websocket library, nothing downloaded. The events we assert on (console
errors, uncaught exceptions, failed loads, every request URL) arrive on the same pipe.
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Optional

CHROMIUM = os.environ.get("COBGS_CHROMIUM", "/usr/bin/chromium")
FLAGS = ("--headless", "--no-sandbox", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--hide-scrollbars", "--mute-audio",
         "--allow-file-access-from-files", "--remote-debugging-pipe")


#: WebGL without a GPU: ANGLE on SwiftShader, Chromium's CPU implementation of Vulkan / GLES
WEBGL_FLAGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist")
NO_GPU_FLAGS = ("--disable-gpu",)


class BrowserError(RuntimeError):
    pass


class Browser:
    """One headless Chromium with one page. Use as a context manager.

    Args:
        width_px, height_px: viewport size.
        timeout_s: limit for any single protocol call or page load.
        webgl: start with WebGL on SwiftShader (else with the GPU process disabled).
    """

    def __init__(self, width_px: int = 1280, height_px: int = 900, timeout_s: float = 45.0,
                 binary: str = CHROMIUM, webgl: bool = False):
        self.width_px, self.height_px, self.timeout_s, self.binary = width_px, height_px, timeout_s, binary
        self.flags = FLAGS + (WEBGL_FLAGS if webgl else NO_GPU_FLAGS)
        self.events: list[dict] = []
        self._next_id = 0
        self._buf = b""
        self._proc: Optional[subprocess.Popen] = None
        self._profile: Optional[str] = None
        self.session: Optional[str] = None

    # -- process -----------------------------------------------------------------------
    def __enter__(self) -> "Browser":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        if not Path(self.binary).exists():
            raise BrowserError(f"{self.binary} not found (install Debian's chromium package)")
        self._profile = tempfile.mkdtemp(prefix="cobgs-chromium-")
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()

        def wire_fds():  # in the child: the protocol pipes must be fds 3 and 4
            a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)
            os.dup2(a, 3)
            os.dup2(b, 4)
            os.set_inheritable(3, True)
            os.set_inheritable(4, True)

        self._log = open(Path(self._profile) / "chromium.log", "wb")
        self._proc = subprocess.Popen(
            [self.binary, *self.flags, f"--user-data-dir={self._profile}",
             f"--window-size={self.width_px},{self.height_px}", "about:blank"],
            preexec_fn=wire_fds, close_fds=False, stdin=subprocess.DEVNULL, stdout=self._log,
            stderr=subprocess.STDOUT)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        targets = self.call("Target.getTargets", session=False)["targetInfos"]
        pages = [t for t in targets if t["type"] == "page"]
        target = pages[0]["targetId"] if pages else self.call(
            "Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                 session=False)["sessionId"]
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.call(f"{domain}.enable")
        self.call("Emulation.setDeviceMetricsOverride", {"width": self.width_px, "height": self.height_px,
                                                         "deviceScaleFactor": 1, "mobile": False})

    def close(self) -> None:
        if self._proc is not None:
            try:
                if self._proc.poll() is None:
                    self._send({"id": self._id(), "method": "Browser.close", "params": {}})
                    self._proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
            for fd in (self._to_chrome, self._from_chrome):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._proc = None
            self._log.close()
        if self._profile:
            shutil.rmtree(self._profile, ignore_errors=True)
            self._profile = None

    # -- protocol ----------------------------------------------------------------------
    def _id(self) -> int:
        self._next_id += 1
        return self._next_id

    def _send(self, msg: dict) -> None:
        data = json.dumps(msg).encode() + b"\0"
        while data:
            n = os.write(self._to_chrome, data)
            data = data[n:]

    def _read(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError("timed out waiting for Chromium")
            ready, _, _ = select.select([self._from_chrome], [], [], left)
            if ready:
                chunk = os.read(self._from_chrome, 1 << 20)
                if not chunk:
                    raise BrowserError(f"Chromium exited (code {self._proc.poll() if self._proc else '?'})")
                self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, params: Optional[dict] = None, session: bool = True) -> dict:
        """Send a command and return its result; events that arrive meanwhile are kept."""
        msg_id = self._id()
        msg: dict[str, Any] = {"id": msg_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = self.session
        self._send(msg)
        deadline = time.monotonic() + self.timeout_s
        while True:
            reply = self._read(deadline)
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            if "method" in reply:
                self.events.append(reply)

    def wait_event(self, method: str, since: int = 0) -> dict:
        deadline = time.monotonic() + self.timeout_s
        while True:
            for ev in self.events[since:]:
                if ev.get("method") == method:
                    return ev
            since = len(self.events)
            ev = self._read(deadline)
            if "method" in ev:
                self.events.append(ev)

    # -- page --------------------------------------------------------------------------
    def goto(self, url: str) -> None:
        mark = len(self.events)
        res = self.call("Page.navigate", {"url": url})
        if res.get("errorText"):
            raise BrowserError(f"navigation to {url} failed: {res['errorText']}")
        self.wait_event("Page.loadEventFired", since=mark)

    def eval(self, expression: str) -> Any:
        res = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in res:
            raise BrowserError(f"{expression!r} raised: {res['exceptionDetails'].get('text')} "
                               f"{res['exceptionDetails'].get('exception', {}).get('description', '')}")
        return res["result"].get("value")

    def click(self, selector: str) -> None:
        ok = self.eval(f"(function(){{var e=document.querySelector({json.dumps(selector)});"
                       f"if(!e) return false; e.click(); return true;}})()")
        if not ok:
            raise BrowserError(f"nothing matches {selector!r}")

    def screenshot(self, path: Path, full_page: bool = True) -> Path:
        if full_page:
            size = self.call("Page.getLayoutMetrics")["cssContentSize"]
            self.call("Emulation.setDeviceMetricsOverride", {
                "width": self.width_px, "height": int(min(size["height"], 16000)), "deviceScaleFactor": 1,
                "mobile": False})
        data = self.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": full_page})["data"]
        if full_page:
            self.call("Emulation.setDeviceMetricsOverride", {"width": self.width_px, "height": self.height_px,
                                                             "deviceScaleFactor": 1, "mobile": False})
        path = Path(path)
        path.write_bytes(base64.b64decode(data))
        return path

    def errors(self) -> list[str]:
        """Console errors, uncaught exceptions and failed loads seen so far."""
        out = []
        for ev in self.events:
            m, p = ev.get("method"), ev.get("params", {})
            if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console." + p["type"] + ": " + " ".join(str(a.get("value", a.get("description", "")))
                                                                    for a in p.get("args", [])))
            elif m == "Runtime.exceptionThrown":
                d = p.get("exceptionDetails", {})
                out.append("exception: " + str(d.get("exception", {}).get("description") or d.get("text")))
            elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                e = p["entry"]
                out.append(f"log[{e.get('source')}]: {e.get('text')} {e.get('url', '')}")
            elif m == "Network.loadingFailed" and not p.get("canceled"):
                out.append(f"load failed: {p.get('errorText')} (request {p.get('requestId')})")
        return out

    def requested_urls(self) -> list[str]:
        return [ev["params"]["request"]["url"] for ev in self.events
                if ev.get("method") == "Network.requestWillBeSent"]
